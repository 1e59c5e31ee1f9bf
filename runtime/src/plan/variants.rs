//! A plan's variants as the runtime reads them: per variant, a dense map from the tensor
//! index a step names to the tensor it reads, built once when the plan is built, and the
//! key lookups (a binary search over canonical text, allocation-free, or by meaning).

use std::fmt;

use readi_plan::VariantKey;
use readi_plan::format::Manifest;

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
}

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
        VariantMaps { keys, parsed, by_key: by_key.into(), maps: maps.into(), span, zero: Box::default() }
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
        Some(VariantTensors { plan: self, map, index: i })
    }

    /// The base model's tensors (variant 0).
    pub fn base_tensors(&self) -> VariantTensors<'_> {
        let span = self.variants.span;
        VariantTensors { plan: self, map: &self.variants.maps[..span], index: 0 }
    }
}
