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
//! Plans are untrusted input: [`Plan::load`] checks the container, the version and the
//! checksum, then the manifest with `readi_plan::validate` (every index, the schedule,
//! and every step's shapes against its operator's shape rule, on the symbolic shapes, so
//! they hold at every batch size), and reports a [`PlanError`] naming what is wrong.
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

use std::collections::HashMap;
use std::fmt;
use std::ops::Range;
use std::path::Path;
use std::sync::Arc;

use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use readi_plan::VariantKey;
pub use readi_plan::format::*;
pub use readi_plan::{Dim, show_shape};

const KEY_VERSION: &str = "readi.format_version";
const KEY_MANIFEST: &str = "readi.manifest";
const KEY_CHECKSUM: &str = "readi.checksum";

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
    Owned(Vec<Arc<[f32]>>),
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
}

impl VariantMaps {
    /// Builds the maps of a validated manifest.
    fn build(m: &Manifest) -> VariantMaps {
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
        VariantMaps { keys, parsed, by_key: by_key.into(), maps: maps.into(), span }
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
    /// A plan from the compiler: the manifest and the data of each manifest tensor, in
    /// manifest order (shared data, such as the compiler's `Arc<[f32]>`, is not copied).
    pub fn new<T: Into<Arc<[f32]>>>(manifest: Manifest, tensors: Vec<T>) -> Result<Plan, PlanError> {
        let tensors = tensors.into_iter().map(Into::into).collect();
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

    /// The index of the variant whose key's canonical text is `key` ([`BASE_VARIANT`] is
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

    /// Checks the manifest ([`readi_plan::validate`]: indices, schedule, every step's
    /// shapes against its operator's rule, its tensors' sizes, BatchNorm records, variant
    /// tables) and, for a plan from the compiler, that each tensor's data fills its shape.
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
        readi_plan::validate::manifest(m).map_err(|detail| PlanError::Manifest { path: path.into(), detail })?;
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
