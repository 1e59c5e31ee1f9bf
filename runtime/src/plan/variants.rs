//! A plan's variants as the runtime reads them: per variant, a dense map from the tensor
//! index a step names to the tensor it reads, built once when the plan is built, and the
//! key lookups (a binary search over canonical text, allocation-free, or by meaning).

use std::fmt;

use half::slice::HalfFloatSliceExt;
use readi_plan::VariantKey;
use readi_plan::format::Manifest;
use readi_plan::ops::DType;

use super::{Kernel, Plan};

/// Per variant, which stored tensor a step's tensor index resolves to; built once at
/// construction so runs resolve with one array lookup and switching is a key lookup.
#[derive(Default)]
pub(super) struct VariantMaps {
    /// Key of each variant: [`BASE_VARIANT`](readi_plan::format::BASE_VARIANT), then the tables' keys in manifest order.
    keys: Box<[Box<str>]>,
    /// The same keys, parsed, for lookups by meaning.
    parsed: Box<[VariantKey]>,
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
    /// Per tensor below `span`, whether it is the `up` projection (weight or bias) of a
    /// fused adapter or the `B` of a LoRA branch and all zeros in the base model: what an
    /// adaptation rule adds is zero until a variant gives it, and a variant that does not
    /// reads that zero ([`VariantTensors::reads_zero`]).
    zero: Box<[bool]>,
    /// Per stored tensor, whether it is f16 (a variant's replacement); empty when none is.
    half: Box<[bool]>,
    /// Per tensor below `span`, the decoded copy ([`Decoded`]) a variant that replaces it
    /// with an f16 tensor reads, [`NO_COPY`] for the others; empty when no tensor is f16.
    copy_of: Box<[u32]>,
    /// Per decoded copy, the base tensor it stands for.
    copies: Box<[u32]>,
}

/// [`VariantMaps::copy_of`] of a tensor no variant replaces by an f16 one.
const NO_COPY: u32 = u32::MAX;

impl VariantMaps {
    /// Builds the maps of a validated manifest.
    pub(super) fn build(m: &Manifest) -> VariantMaps {
        // Without variants every lookup falls through to the identity: no map at all.
        let span = if m.variants.is_empty() { 0 } else { readi_plan::validate::map_span(m) };
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
        let parsed: Box<[VariantKey]> =
            std::iter::once(VariantKey::base()).chain(m.variants.iter().map(|v| v.key.clone())).collect();
        let keys: Box<[Box<str>]> = parsed.iter().map(|k| k.to_string().into_boxed_str()).collect();
        let mut by_key: Vec<u32> = (0..count as u32).collect();
        by_key.sort_by(|&a, &b| key_order(&keys[a as usize], &keys[b as usize]));
        VariantMaps {
            keys,
            parsed,
            by_key: by_key.into(),
            maps: maps.into(),
            span,
            zero: Box::default(),
            half: Box::default(),
            copy_of: Box::default(),
            copies: Box::default(),
        }
    }

    /// Records the f16 tensors and gives every base tensor some variant replaces by one a
    /// decoded copy.
    pub(super) fn mark_half(&mut self, m: &Manifest) {
        if m.tensors.iter().all(|t| t.dtype == DType::F32) {
            return;
        }
        let half: Box<[bool]> = m.tensors.iter().map(|t| t.dtype == DType::F16).collect();
        let mut copy_of = vec![NO_COPY; self.span];
        let mut copies = Vec::new();
        for r in m.variants.iter().flat_map(|v| &v.replaces) {
            // Validation: `base` is below `span`, `with` a stored tensor.
            if half[r.with] && copy_of[r.base] == NO_COPY {
                copy_of[r.base] = copies.len() as u32;
                copies.push(r.base as u32);
            }
        }
        self.half = half;
        self.copy_of = copy_of.into();
        self.copies = copies.into();
    }

    /// Marks the base model's all-zero adapter up-projections and LoRA `B`s among the
    /// tensors the steps name (`is_zero(t)`: tensor `t`'s base data are all zeros). Reads
    /// only those tensors, not the plan.
    pub(super) fn mark_zeros(&mut self, m: &Manifest, is_zero: impl Fn(usize) -> bool) {
        let mut zero = vec![false; self.span];
        let mut mark = |t: usize| {
            if t < zero.len() && !zero[t] {
                zero[t] = is_zero(t);
            }
        };
        for step in &m.steps {
            match &step.kernel {
                Kernel::Conv2d { lora, adapter, .. } => {
                    if let Some(a) = adapter {
                        mark(a.up);
                        mark(a.up_bias);
                    }
                    if let Some(l) = lora {
                        mark(l.b);
                    }
                }
                Kernel::Linear { lora: Some(l), .. } => mark(l.b),
                _ => {}
            }
        }
        self.zero = zero.into();
    }
}

/// The order of the key lookup table: by length, then by bytes, so that most comparisons
/// of a lookup are decided by the lengths.
fn key_order(a: &str, b: &str) -> std::cmp::Ordering {
    a.len().cmp(&b.len()).then_with(|| a.cmp(b))
}

/// The stored tensors as one variant sees them: where a step names tensor `t`, the
/// variant reads [`resolve(t)`](VariantTensors::resolve). Cheap to copy.
///
/// A replacement stored as f16 is read from the session's decoded copy of it
/// ([`Decoded`]); without one ([`Plan::variant_tensors`] alone) it reads as empty.
#[derive(Clone, Copy)]
pub struct VariantTensors<'a> {
    plan: &'a Plan,
    map: &'a [u32],
    index: usize,
    decoded: &'a [Vec<f32>],
}

/// Values per task of a decode ([`Decoded::refresh`]).
const DECODE_CHUNK: usize = 1 << 16;

/// A session's f32 copies of the active variant's f16 replacements: one per base tensor
/// some variant replaces by an f16 tensor (whatever the number of variants), written at
/// the start of a run whose variant differs from the one they hold, before any step, so
/// a run never sees a half-written copy. Allocated by the session's first run, after its
/// footprint (which counts them) passed the memory limit; a switch then writes into them
/// and allocates nothing.
#[derive(Default)]
pub(crate) struct Decoded {
    variant: Option<usize>,
    copies: Vec<Vec<f32>>,
}

impl Decoded {
    /// Decodes variant `variant`'s f16 replacements, unless the copies hold them already;
    /// a large one on the threads of `pool`.
    pub(crate) fn refresh(&mut self, plan: &Plan, variant: usize, pool: &rayon::ThreadPool) {
        let maps = &plan.variants;
        if maps.copies.is_empty() || self.variant == Some(variant) {
            return;
        }
        if self.copies.is_empty() {
            self.copies = Decoded::lens(plan).map(|n| vec![0.0; n]).collect();
        }
        let Some(tensors) = plan.variant_tensors(variant) else { return };
        for (copy, &base) in self.copies.iter_mut().zip(&maps.copies) {
            // A variant that keeps the base's tensor, or replaces it by an f32 one, reads
            // that tensor directly, not the copy.
            let Some(half) = plan.tensor_f16(tensors.resolve(base as usize)) else { continue };
            if half.len() < 2 * DECODE_CHUNK {
                half.convert_to_f32_slice(copy);
            } else {
                // On the session's threads, in chunks: ResNet-18's 1000-class fc (0.5 M
                // values) took 0.16 ms on one thread.
                use rayon::prelude::*;
                pool.install(|| {
                    copy.par_chunks_mut(DECODE_CHUNK)
                        .zip(half.par_chunks(DECODE_CHUNK))
                        .for_each(|(c, h)| h.convert_to_f32_slice(c))
                });
            }
        }
        self.variant = Some(variant);
    }

    /// Floats of each copy a session of `plan` keeps (its base tensor's).
    fn lens(plan: &Plan) -> impl Iterator<Item = usize> + '_ {
        plan.variants.copies.iter().map(|&b| plan.manifest.tensors[b as usize].numel())
    }

    /// Bytes of the copies a session of `plan` keeps.
    pub(crate) fn bytes(plan: &Plan) -> usize {
        Decoded::lens(plan).fold(0usize, |a, n| a.saturating_add(n.saturating_mul(4)))
    }

    /// The copies, for [`VariantTensors::with_decoded`].
    pub(crate) fn copies(&self) -> &[Vec<f32>] {
        &self.copies
    }
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
        let s = self.resolve(t);
        if self.plan.variants.half.get(s).copied().unwrap_or(false) {
            let copy = self.plan.variants.copy_of.get(t).copied().unwrap_or(NO_COPY);
            return self.decoded.get(copy as usize).map_or(&[], Vec::as_slice);
        }
        self.plan.f32_data(s)
    }

    /// The same tensors, reading the f16 replacements from `copies` (a session's
    /// [`Decoded`], refreshed for this variant).
    pub(crate) fn with_decoded(self, copies: &'a [Vec<f32>]) -> VariantTensors<'a> {
        VariantTensors { decoded: copies, ..self }
    }

    /// Whether this variant reads the base model's value of the adapter up-projection or
    /// LoRA `B` named `t`, and that value is all zeros: an adapter whose `up` and `up_bias`
    /// both read zero is the identity, a branch whose `B` does adds zero, so the kernels
    /// skip them (a variant pays only for the adaptations it has; 0 · ∞ aside, which the
    /// skipped branch would have turned into NaN, the output is the same).
    #[inline]
    pub fn reads_zero(&self, t: usize) -> bool {
        self.resolve(t) == t && self.plan.variants.zero.get(t).copied().unwrap_or(false)
    }
}

impl fmt::Debug for VariantTensors<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("VariantTensors").field("index", &self.index).field("key", &self.key()).finish()
    }
}

impl Plan {
    /// Number of variants including the base; their indices are `0..variant_count()`.
    pub fn variant_count(&self) -> usize {
        self.variants.keys.len()
    }

    /// The index of the variant whose key's canonical text is `key` ([`BASE_VARIANT`](readi_plan::format::BASE_VARIANT) is
    /// 0); [`Plan::variant_index_of`] takes a parsed key. Allocates nothing.
    pub fn variant_index(&self, key: &str) -> Option<usize> {
        let keys = &self.variants.keys;
        let at = self.variants.by_key.binary_search_by(|&i| key_order(&keys[i as usize], key)).ok()?;
        Some(self.variants.by_key[at] as usize)
    }

    /// The index of the variant of key `key` (the base is 0), compared as keys, not as
    /// text. Allocates nothing.
    pub fn variant_index_of(&self, key: &VariantKey) -> Option<usize> {
        self.variants.parsed.iter().position(|k| k == key)
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
        Some(VariantTensors { plan: self, map, index: i, decoded: &[] })
    }

    /// The base model's tensors (variant 0).
    pub fn base_tensors(&self) -> VariantTensors<'_> {
        let span = self.variants.span;
        VariantTensors { plan: self, map: &self.variants.maps[..span], index: 0, decoded: &[] }
    }
}
