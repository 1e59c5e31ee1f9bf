//! Checking a manifest before anything runs it.
//!
//! Plans are untrusted input: a corrupted or hand-edited file must be refused with a
//! message naming the step, value or tensor at fault, never reach a kernel with sizes it
//! does not expect. [`manifest`] checks, in order:
//!
//! 1. the symbols are distinct identifiers; there are no more activation buffers (slots)
//!    than values; every index (inputs, values, slots, tensors) is in range, and every
//!    dimension is a non-negative coefficient over declared symbols;
//! 2. input names are unique, and so are output names; each input's declared shape is its
//!    value's, and a value stored as a tensor has the tensor's (known) shape;
//! 3. the schedule: each step writes an activation buffer not written before, reads only
//!    values already written, and does not read the buffer it writes;
//! 4. each step's output shape is what its operator's shape rule ([`crate::ops`]) computes
//!    from its inputs' shapes (symbolically, so it holds for every batch size), and the
//!    stored tensors it reads have the sizes its kernel needs (a fused LoRA branch: a rank
//!    of 1 to `MAX_LORA_RANK`, one group, `A` packed for the algorithm, `B` of `out · rank`);
//! 5. folded BatchNorm records ([`BnInfo`]) sit on conv or channel-affine steps with a
//!    scale and a shift, with unique names, a finite eps and tensors of the scale's shape;
//! 6. variant tables: keys unique and not `base`, replacements of tensors some step reads,
//!    at most once each, by tensors of exactly their shape (so checking the base covers
//!    every variant); every stored tensor is f32 but a replacement's, which may be f16
//!    (and then is nothing else: not named by a step, a value, a BatchNorm record or as
//!    a replaced base);
//! 7. the conditions block, which variant selection reads without further checks: axes
//!    with unique identifier names, a modality and distinct finite levels; one selector
//!    at most per declared axis, reading an input the plan has (or a named metadata
//!    value), with finite thresholds and arm levels among the axis's; missing-modality
//!    policies for modalities of optional inputs, once each; a meld rule whose lambdas
//!    are finite, positive and name modalities or axes the conditions declare; and every
//!    variant key made of declared axis levels and missing modalities;
//! 8. parameter ownership ([`crate::format::ParamSpec::owned_by`]): each scope name is
//!    `missing`, `missing=M` for a modality `M` of an input, or the name of an axis or of
//!    a modality (of an axis or an input), so every key can be decided.
//!
//! Nothing here depends on the kernels' code: a conv's packed weight length is
//! [`crate::ops::ConvAlgo::packed_len`], defined with the algorithms.

use std::collections::HashSet;

use crate::conditions::{KeySource, MeldBy, MissingPolicy};
use crate::dim::Dim;
use crate::format::{
    AdapterSpec, BASE_VARIANT, EpilogueSpec, Kernel, LoraSpec, MAX_LORA_RANK, Manifest, Step, Storage, escaped,
};
use crate::key::{KeyPart, MISSING_AXIS};
use crate::ops::{self, Conv2dShape, ConvAlgo, DType, TensorType};

/// Most entries the runtime's variant maps may take together (variants x mapped
/// tensors): 256 MiB. A real plan needs a few thousand; the bound keeps a small crafted
/// manifest from asking for an enormous allocation.
pub const MAX_MAP_ENTRIES: usize = 1 << 26;

/// Checks a manifest; the error says what is wrong and where.
pub fn manifest(m: &Manifest) -> Result<(), String> {
    indices(m)?;
    schedule(m)?;
    batchnorms(m)?;
    variants(m)?;
    conditions(m)?;
    ownership(m)
}

fn bad_dim(d: &Dim, symbols: &[String]) -> bool {
    d.coef() < 0 || d.symbols().iter().any(|s| !symbols.contains(s))
}

/// An identifier: ASCII letters, digits and `_`, not starting with a digit.
fn is_identifier(s: &str) -> bool {
    let mut chars = s.chars();
    chars.next().is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && chars.all(|c| c.is_ascii_alphanumeric() || c == '_')
}

/// 1 and 2.
fn indices(m: &Manifest) -> Result<(), String> {
    let nv = m.values.len();
    if m.slots > nv {
        return Err(format!("{} activation buffers for {nv} values: a plan has at most one per value", m.slots));
    }
    for (i, s) in m.symbols.iter().enumerate() {
        if !is_identifier(s) || m.symbols[..i].contains(s) {
            return Err(format!("symbol `{}` is not an identifier, or is declared twice", escaped(s)));
        }
    }
    let mut names: HashSet<&str> = HashSet::new();
    for inp in &m.inputs {
        if !names.insert(&inp.name) {
            return Err(format!("input `{}` is declared twice", escaped(&inp.name)));
        }
    }
    names.clear();
    for o in &m.outputs {
        if !names.insert(&o.name) {
            return Err(format!("output `{}` is declared twice", escaped(&o.name)));
        }
    }
    for (i, inp) in m.inputs.iter().enumerate() {
        if inp.value >= nv || m.values[inp.value].storage != Storage::Input(i) {
            return Err(format!("input `{}` refers to an invalid value", escaped(&inp.name)));
        }
        if let Some(d) = inp.shape.iter().find(|d| bad_dim(d, &m.symbols)) {
            return Err(format!("input `{}` has an invalid dimension {d}", escaped(&inp.name)));
        }
        if inp.shape != m.values[inp.value].shape {
            return Err(format!(
                "input `{}` is declared as {} but its value has shape {}",
                escaped(&inp.name),
                crate::show_shape(&inp.shape),
                crate::show_shape(&m.values[inp.value].shape)
            ));
        }
    }
    for (i, v) in m.values.iter().enumerate() {
        match v.storage {
            Storage::Input(k) if k >= m.inputs.len() => return Err(format!("value {i} reads input {k}")),
            Storage::Slot(s) if s >= m.slots => return Err(format!("value {i} uses slot {s} of {}", m.slots)),
            Storage::Tensor(t) if t >= m.tensors.len() => return Err(format!("value {i} reads tensor {t}")),
            Storage::Tensor(t) => {
                let shape: Vec<Dim> = m.tensors[t].shape.iter().map(|&d| Dim::from(d)).collect();
                if shape != v.shape {
                    return Err(format!(
                        "value {i} is stored tensor `{}` of shape {:?}, but has shape {}",
                        escaped(&m.tensors[t].name),
                        m.tensors[t].shape,
                        crate::show_shape(&v.shape)
                    ));
                }
            }
            _ => {}
        }
        if let Some(d) = v.shape.iter().find(|d| bad_dim(d, &m.symbols)) {
            return Err(format!("value {i} has an invalid dimension {d}"));
        }
    }
    Ok(())
}

/// 3 and 4.
fn schedule(m: &Manifest) -> Result<(), String> {
    let nv = m.values.len();
    let mut written = vec![false; nv];
    for inp in &m.inputs {
        written[inp.value] = true;
    }
    for (i, v) in m.values.iter().enumerate() {
        if matches!(v.storage, Storage::Tensor(_)) {
            written[i] = true;
        }
    }
    for (k, step) in m.steps.iter().enumerate() {
        let at = format!("step {k} (`{}`)", escaped(&step.path));
        let Some(Storage::Slot(out_slot)) = m.values.get(step.output).map(|v| v.storage) else {
            return Err(format!("{at} writes an invalid value"));
        };
        if written[step.output] {
            return Err(format!("{at} writes value {} a second time", step.output));
        }
        for &i in &step.inputs {
            if i >= nv || !written[i] {
                return Err(format!("{at} reads value {i} before it is written"));
            }
            if m.values[i].storage == Storage::Slot(out_slot) && !step.is_view(&m.values) {
                return Err(format!("{at} reads buffer {out_slot}, which it writes"));
            }
        }
        for t in step.kernel.tensors() {
            if t >= m.tensors.len() {
                return Err(format!("{at} reads tensor {t} of {}", m.tensors.len()));
            }
        }
        let inputs: Vec<TensorType> = step.inputs.iter().map(|&i| TensorType::f32(m.values[i].shape.clone())).collect();
        let refs: Vec<&TensorType> = inputs.iter().collect();
        let out = &m.values[step.output].shape;
        let want = match &step.kernel {
            Kernel::Conv2d { conv, residual, channel_scale, .. } => conv.infer_fused(&refs, *residual, *channel_scale),
            k => ops::infer(k.op(), &refs),
        }
        .map_err(|e| format!("{at}: {e}"))?;
        if &want.shape != out {
            return Err(format!(
                "{at}: its output has shape {}, but {} of its inputs gives {}",
                crate::show_shape(out),
                step.kernel.op().kind_name(),
                crate::show_shape(&want.shape)
            ));
        }
        tensor_sizes(m, step).map_err(|e| format!("{at}: {e}"))?;
        written[step.output] = true;
    }
    for o in &m.outputs {
        if o.value >= nv || !written[o.value] {
            return Err(format!("output `{}` is never computed", escaped(&o.name)));
        }
    }
    Ok(())
}

/// The stored tensors of a step's kernel have the sizes it reads (step 4), a conv's
/// packed weight the length its algorithm reads, and the algorithm fits the layer.
fn tensor_sizes(m: &Manifest, step: &Step) -> Result<(), String> {
    let kernel = &step.kernel;
    let numel = |t: usize| m.tensors[t].numel();
    let per_channel = |ep: &EpilogueSpec, channels: i64| -> Result<(), String> {
        if let Some(act) = ep.act {
            act.check_options().map_err(|e| format!("epilogue: {e}"))?;
        }
        for t in ep.scale.into_iter().chain(ep.shift) {
            if numel(t) as u64 != channels as u64 {
                return Err(format!(
                    "epilogue tensor `{}` has {} values for {channels} channels",
                    escaped(&m.tensors[t].name),
                    numel(t)
                ));
            }
        }
        Ok(())
    };
    match kernel {
        Kernel::Conv2d { conv, algo, weight, epilogue, lora, switch, adapter, .. } => {
            // The shape rule has checked the spatial sizes are known; the batch does not matter.
            let x = &m.values[step.inputs[0]].shape;
            let known = |d: &Dim| d.as_known().and_then(|v| usize::try_from(v).ok()).unwrap_or(0);
            let s = conv.shape(1, known(&x[2]), known(&x[3]));
            if !algo.supports(&s) {
                return Err(format!("conv algorithm `{}` cannot compute this layer", algo.name()));
            }
            // Merged on switch, the weight is stored raw (PyTorch's layout, what im2col reads).
            let (stored, how) = if *switch { (ConvAlgo::Im2col, "raw") } else { (*algo, algo.name()) };
            if numel(*weight) != stored.packed_len(&s) {
                return Err(format!(
                    "conv2d weight `{}` has {} values, `{how}` needs {}",
                    escaped(&m.tensors[*weight].name),
                    numel(*weight),
                    stored.packed_len(&s)
                ));
            }
            if let Some(l) = lora {
                if conv.groups != 1 || *algo == ConvAlgo::Depthwise {
                    return Err(format!(
                        "a fused LoRA branch on a conv with {} groups, algorithm `{}`: it needs one group and not \
                         the depthwise loop",
                        conv.groups,
                        algo.name()
                    ));
                }
                if *switch && !l.a_raw {
                    return Err(format!(
                        "LoRA A `{}` of a conv merged on switch must be stored raw (`a_raw`)",
                        escaped(&m.tensors[l.a].name)
                    ));
                }
                // A raw `A` is PyTorch's layout, what the im2col algorithm reads.
                let a = Conv2dShape { cout: l.rank, ..s };
                let layout = algo.lora_a_layout();
                let (stored, how) = if l.a_raw { (ConvAlgo::Im2col, "raw") } else { (layout, layout.name()) };
                lora_sizes(m, l, stored.packed_len(&a), conv.out_channels, how)?;
            }
            if let Some(a) = adapter {
                adapter_sizes(m, a, conv.out_channels)?;
            }
            per_channel(epilogue, conv.out_channels)
        }
        Kernel::ConvTranspose2d { conv, weight, epilogue } => {
            // The shape rule has checked channels, groups and stride; the batch does not matter.
            let x = &m.values[step.inputs[0]].shape;
            let known = |d: &Dim| d.as_known().and_then(|v| usize::try_from(v).ok()).unwrap_or(0);
            let want = conv.shape(1, known(&x[2]), known(&x[3])).weight_len();
            if numel(*weight) != want {
                return Err(format!(
                    "conv_transpose2d weight `{}` has {} values (shape {:?}), it needs {want} ({:?})",
                    escaped(&m.tensors[*weight].name),
                    numel(*weight),
                    m.tensors[*weight].shape,
                    conv.weight_shape()
                ));
            }
            per_channel(epilogue, conv.out_channels)
        }
        Kernel::Conv3d { conv, weight, epilogue } => {
            // The shape rule has checked channels and groups; the weight does not depend
            // on the input's size.
            let want = conv.weight_len();
            if numel(*weight) as u64 != want {
                return Err(format!(
                    "conv3d weight `{}` has {} values (shape {:?}), it needs {want} ({:?})",
                    escaped(&m.tensors[*weight].name),
                    numel(*weight),
                    m.tensors[*weight].shape,
                    conv.weight_shape()
                ));
            }
            per_channel(epilogue, conv.out_channels)
        }
        Kernel::Linear { linear, weight, epilogue, lora, panels } => {
            let want = if *panels {
                linear.panel_len().map_or(u64::MAX, |n| n as u64)
            } else {
                (linear.in_features as u64).saturating_mul(linear.out_features as u64)
            };
            if numel(*weight) as u64 != want {
                let layout = if *panels { " (in panels)" } else { "" };
                return Err(format!(
                    "linear weight `{}` has {} values, not {want}{layout}",
                    escaped(&m.tensors[*weight].name),
                    numel(*weight)
                ));
            }
            if let Some(l) = lora {
                if l.a_raw {
                    return Err(format!(
                        "a linear's LoRA A `{}` cannot be stored raw (`a_raw` is for convs)",
                        escaped(&m.tensors[l.a].name)
                    ));
                }
                let a = (linear.in_features.max(0) as usize).saturating_mul(l.rank);
                lora_sizes(m, l, a, linear.out_features, "linear")?;
            }
            per_channel(epilogue, linear.out_features)
        }
        Kernel::ChannelAffine { affine, epilogue } => per_channel(epilogue, affine.channels),
        Kernel::LayerNorm { norm, weight, bias } => {
            if weight.is_some() != norm.affine || bias.is_some() != norm.affine {
                return Err("layernorm parameters do not match its `affine`".into());
            }
            for t in weight.iter().chain(bias) {
                if numel(*t) as u64 != norm.features as u64 {
                    return Err(format!(
                        "layernorm parameters have the wrong size ({} for {})",
                        numel(*t),
                        norm.features
                    ));
                }
            }
            Ok(())
        }
        Kernel::GroupNorm { norm, weight, bias } => {
            if weight.is_some() != norm.affine || bias.is_some() != norm.affine {
                return Err("groupnorm parameters do not match its `affine`".into());
            }
            for t in weight.iter().chain(bias) {
                if numel(*t) as u64 != norm.num_channels.max(0) as u64 {
                    return Err(format!(
                        "groupnorm tensor `{}` has {} values for {} channels",
                        escaped(&m.tensors[*t].name),
                        numel(*t),
                        norm.num_channels
                    ));
                }
            }
            Ok(())
        }
        Kernel::Pure(_) => Ok(()),
    }
}

/// A fused LoRA branch: a rank of 1 to [`MAX_LORA_RANK`], `A` of `a_len` values (packed
/// for `how`), `B` of `out · rank`. The tensor indices were checked with the step's.
fn lora_sizes(m: &Manifest, l: &LoraSpec, a_len: usize, out: i64, how: &str) -> Result<(), String> {
    if l.rank == 0 || l.rank > MAX_LORA_RANK {
        return Err(format!("LoRA rank {}: it must be 1 to {MAX_LORA_RANK}", l.rank));
    }
    let (na, nb) = (m.tensors[l.a].numel(), m.tensors[l.b].numel());
    let b_len = (out.max(0) as usize).saturating_mul(l.rank);
    if na != a_len || nb != b_len {
        return Err(format!(
            "LoRA A `{}` has {na} values (`{how}` at rank {} needs {a_len}), B `{}` {nb} (needs {b_len})",
            escaped(&m.tensors[l.a].name),
            l.rank,
            escaped(&m.tensors[l.b].name)
        ));
    }
    Ok(())
}

/// A fused adapter on a conv of `cout` channels: `mid` of 1 to `cout`, `down` of
/// `[mid, cout]`, `up` of `[cout, mid]`, biases of `[mid]` and `[cout]` (as element
/// counts: a 1x1 conv's weight `[mid, cout, 1, 1]` is `[mid, cout]`). The tensor indices
/// were checked with the step's.
fn adapter_sizes(m: &Manifest, a: &AdapterSpec, cout: i64) -> Result<(), String> {
    let c = cout.max(0) as usize;
    if a.mid == 0 || a.mid > c {
        return Err(format!("adapter bottleneck of {} channels: it must be 1 to the conv's {c}", a.mid));
    }
    let mc = a.mid.saturating_mul(c);
    let want = [("down", a.down, mc, [a.mid, c]), ("down bias", a.down_bias, a.mid, [a.mid, 1])];
    let want_up = [("up", a.up, mc, [c, a.mid]), ("up bias", a.up_bias, c, [c, 1])];
    for (what, t, n, shape) in want.into_iter().chain(want_up) {
        let got = m.tensors[t].numel();
        if got != n {
            let shape = if shape[1] == 1 { format!("[{}]", shape[0]) } else { format!("[{}, {}]", shape[0], shape[1]) };
            return Err(format!(
                "adapter {what} `{}` has {got} values (shape {:?}), it needs {shape} ({n}) for {c} channels \
                 and a bottleneck of {}",
                escaped(&m.tensors[t].name),
                m.tensors[t].shape,
                a.mid
            ));
        }
    }
    Ok(())
}

/// 5.
fn batchnorms(m: &Manifest) -> Result<(), String> {
    let mut names: HashSet<&str> = HashSet::new();
    for (k, step) in m.steps.iter().enumerate() {
        let Some(ep) = step.kernel.epilogue() else { continue };
        let Some(bn) = &ep.bn else { continue };
        let at = format!("step {k} (`{}`), BatchNorm `{}`", escaped(&step.path), escaped(&bn.name));
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
                        escaped(&spec.name),
                        spec.shape
                    ));
                }
                Some(_) => {}
            }
        }
    }
    Ok(())
}

/// Which stored tensors the schedule names: read by a step's kernel or stored as a value.
/// Indices out of range are skipped (validation reports them).
pub fn read_tensors(m: &Manifest) -> Vec<bool> {
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

/// One past the highest tensor index the schedule names (0 when it names none): the width
/// of the runtime's variant maps.
pub fn map_span(m: &Manifest) -> usize {
    read_tensors(m).iter().rposition(|&r| r).map_or(0, |t| t + 1)
}

/// 6.
fn variants(m: &Manifest) -> Result<(), String> {
    let n = m.tensors.len();
    half_only_as_replacements(m)?;
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
    let name = |t: usize| escaped(&m.tensors[t].name);
    let mut keys: HashSet<String> = HashSet::with_capacity(m.variants.len());
    let mut replaced = vec![usize::MAX; n];
    for (i, v) in m.variants.iter().enumerate() {
        let key = v.key.to_string();
        let at = format!("variant `{key}`");
        if v.key.is_base() || key == BASE_VARIANT {
            return Err(format!("{at}: the key `{BASE_VARIANT}` is reserved for the base model"));
        }
        if !keys.insert(key) {
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

/// Every stored tensor is f32 but a variant's replacement, which may be f16 and then is
/// read only through the variant tables (a session decodes it into a working copy): no
/// step, value or BatchNorm record names it and no variant replaces it.
fn half_only_as_replacements(m: &Manifest) -> Result<(), String> {
    let mut other = read_tensors(m);
    let bn = m.steps.iter().filter_map(|s| s.kernel.epilogue()?.bn.as_ref()).flat_map(|b| b.tensors());
    let bases = m.variants.iter().flat_map(|v| v.replaces.iter().map(|r| r.base));
    for t in bn.chain(bases) {
        if let Some(o) = other.get_mut(t) {
            *o = true;
        }
    }
    let mut replacement = vec![false; m.tensors.len()];
    for r in m.variants.iter().flat_map(|v| &v.replaces) {
        if let Some(w) = replacement.get_mut(r.with) {
            *w = true;
        }
    }
    for (t, spec) in m.tensors.iter().enumerate() {
        let at = || format!("tensor {t} (`{}`)", escaped(&spec.name));
        match spec.dtype {
            DType::F32 => {}
            DType::F16 if replacement[t] && !other[t] => {}
            DType::F16 => {
                return Err(format!(
                    "{} is stored as f16, which only a variant's replacement may be (the base model and what \
                     its steps name are f32)",
                    at()
                ));
            }
            d => return Err(format!("{} is stored as {}; a plan stores f32 (and f16 replacements)", at(), d.as_str())),
        }
    }
    Ok(())
}

/// 7.
fn conditions(m: &Manifest) -> Result<(), String> {
    let Some(c) = &m.conditions else { return Ok(()) };
    let e = |s: &str| escaped(s).into_owned();
    let modalities: Vec<&str> = m.inputs.iter().filter_map(|i| i.modality.as_deref()).collect();
    for (i, a) in c.axes.iter().enumerate() {
        let at = format!("conditions: axis `{}`", e(&a.name));
        if !is_identifier(&a.name) || c.axes[..i].iter().any(|b| b.name == a.name) {
            return Err(format!("{at}: the name is not an identifier, or is declared twice"));
        }
        if a.modality.is_empty() {
            return Err(format!("{at}: no modality"));
        }
        if a.levels.is_empty() {
            return Err(format!("{at}: no levels"));
        }
        for (j, l) in a.levels.iter().enumerate() {
            if !l.is_finite() || a.levels[..j].contains(l) {
                return Err(format!("{at}: level {l} is not a finite number, or is declared twice"));
            }
        }
        if a.clear.is_some_and(|l| !l.is_finite() || a.levels.contains(&l)) {
            return Err(format!("{at}: the clear level is not finite, or is also a variant level"));
        }
    }
    for (i, s) in c.selectors.iter().enumerate() {
        let at = format!("conditions: the selector of axis `{}`", e(&s.axis));
        let Some(axis) = c.axis(&s.axis) else {
            let known: Vec<String> = c.axes.iter().map(|a| e(&a.name)).collect();
            return Err(format!("{at}: no such axis (the axes: {})", known.join(", ")));
        };
        if c.selectors[..i].iter().any(|o| o.axis == s.axis) {
            return Err(format!("{at}: the axis has two selectors"));
        }
        match &s.source {
            KeySource::Meta(k) => {
                // Dotted paths (`weather.fog_density`) are names too.
                if k.split('.').any(|part| !is_identifier(part)) {
                    return Err(format!("{at}: metadata name `{}` is not a dotted identifier", e(k)));
                }
            }
            KeySource::Stat { input, .. } => {
                if !m.inputs.iter().any(|i| &i.name == input) {
                    let known: Vec<String> = m.inputs.iter().map(|i| e(&i.name)).collect();
                    return Err(format!(
                        "{at} reads input `{}`, which the plan does not have (its inputs: {})",
                        e(input),
                        known.join(", ")
                    ));
                }
            }
        }
        for (j, arm) in s.arms.iter().enumerate() {
            if let Some((t, _)) = arm.below
                && !t.is_finite()
            {
                return Err(format!("{at}: arm {j} has threshold {t}, not a finite number"));
            }
            if arm.below.is_none() && j + 1 != s.arms.len() {
                return Err(format!("{at}: arm {j} has no bound but is not the last"));
            }
            if let Some(l) = arm.level
                && !axis.levels.contains(&l)
            {
                return Err(format!("{at}: arm {j} selects level {l}, which the axis does not declare"));
            }
        }
    }
    for (i, (modality, policy)) in c.missing.iter().enumerate() {
        let at = format!("conditions: the missing policy of `{}`", e(modality));
        if c.missing[..i].iter().any(|(o, _)| o == modality) {
            return Err(format!("{at}: declared twice"));
        }
        let optional = m.inputs.iter().any(|inp| inp.optional && inp.modality.as_deref() == Some(modality.as_str()));
        if *policy == MissingPolicy::Variant && !optional {
            return Err(format!("{at}: no optional input of the plan has this modality"));
        }
    }
    if let Some(meld) = &c.meld {
        for (i, (name, l)) in meld.weights.iter().enumerate() {
            let at = format!("conditions: the meld lambda of `{}`", e(name));
            if !(l.is_finite() && *l > 0.0) {
                return Err(format!("{at}: {l} is not a positive finite number"));
            }
            if meld.weights[..i].iter().any(|(o, _)| o == name) {
                return Err(format!("{at}: declared twice"));
            }
            let known = match meld.by {
                MeldBy::Axis => c.axis(name).is_some(),
                MeldBy::Modality => modalities.contains(&name.as_str()) || c.axes.iter().any(|a| &a.modality == name),
            };
            if !known {
                return Err(format!("{at}: no such {}", if meld.by == MeldBy::Axis { "axis" } else { "modality" }));
            }
        }
    }
    for v in &m.variants {
        for p in v.key.parts() {
            let declared = match p {
                KeyPart::Level { axis, level } => c.axis(axis).is_some_and(|a| a.levels.contains(level)),
                KeyPart::Missing { modality } => {
                    c.missing.iter().any(|(mm, p)| mm == modality && *p == MissingPolicy::Variant)
                }
            };
            if !declared {
                return Err(format!("variant `{}`: its part `{p}` is not declared by the plan's conditions", v.key));
            }
        }
    }
    Ok(())
}

/// 8.
fn ownership(m: &Manifest) -> Result<(), String> {
    let axes = m.conditions.as_ref().map(|c| c.axes.as_slice()).unwrap_or_default();
    let modalities: Vec<&str> =
        m.inputs.iter().filter_map(|i| i.modality.as_deref()).chain(axes.iter().map(|a| a.modality.as_str())).collect();
    let names: Vec<&str> = axes.iter().map(|a| a.name.as_str()).chain(modalities.iter().copied()).collect();
    for p in &m.params {
        for s in p.owned_by.iter().flatten() {
            let known = match s.split_once('=') {
                None => s == MISSING_AXIS || names.contains(&s.as_str()),
                Some((axis, modality)) => axis == MISSING_AXIS && modalities.contains(&modality),
            };
            if !known {
                let mut listed: Vec<String> = Vec::new();
                for n in names.iter().map(|n| escaped(n).into_owned()).chain([MISSING_AXIS.to_string()]) {
                    if !listed.contains(&n) {
                        listed.push(n);
                    }
                }
                return Err(format!(
                    "parameter `{}`: owned by unknown scope `{}` (the plan's scopes: {})",
                    escaped(&p.name),
                    escaped(s),
                    listed.join(", ")
                ));
            }
        }
    }
    Ok(())
}
