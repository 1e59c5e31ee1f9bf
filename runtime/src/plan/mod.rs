//! The plan file: what the compiler emits and the runtime maps into memory.
//!
//! A plan is a [safetensors] file. Its tensors are the stored weights (f32, each stored
//! once; a variant's replacement may be f16, [`TensorSpec::dtype`]); its metadata holds
//! three keys:
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

use half::f16;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};

pub use readi_plan::format::*;
use readi_plan::ops::DType;
pub use readi_plan::{Dim, show_shape};

mod variants;

pub(crate) use variants::Decoded;
use variants::VariantMaps;
pub use variants::VariantTensors;

/// Largest plan file [`Plan::load`] accepts: 64 GiB.
pub const MAX_PLAN_BYTES: u64 = 64 << 30;

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
    /// Not a regular file (a device such as `/dev/zero`, a FIFO, a directory), or one
    /// larger than [`MAX_PLAN_BYTES`].
    NotAFile {
        path: String,
        detail: String,
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

/// Whether this runtime reads plans of format `version` (see [`OLDEST_FORMAT_VERSION`]).
fn readable_version(version: Option<u32>) -> bool {
    version.is_some_and(|v| (OLDEST_FORMAT_VERSION..=FORMAT_VERSION).contains(&v))
}

impl fmt::Display for PlanError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            PlanError::Io { path, error } => write!(f, "{path}: {error}"),
            PlanError::NotAFile { path, detail } => write!(f, "{path}: {detail}"),
            PlanError::Container { path, detail } => {
                let detail = escaped(detail);
                write!(f, "{path}: not a valid plan file ({detail}); the file may be truncated or corrupted")
            }
            PlanError::NotAPlan { path, missing } => {
                write!(f, "{path}: a safetensors file but not a readi plan (no `{missing}` in its metadata)")
            }
            PlanError::Version { path, found } => write!(
                f,
                "{path}: plan format version {}, but this readi reads versions {OLDEST_FORMAT_VERSION} to {FORMAT_VERSION}; recompile the plan",
                escaped(found)
            ),
            PlanError::Manifest { path, detail } => write!(f, "{path}: invalid plan manifest: {detail}"),
            PlanError::Checksum { path, stored, computed } => {
                let stored = escaped(stored);
                write!(f, "{path}: checksum mismatch (stored {stored}, computed {computed:08x}): the file is corrupted")
            }
            PlanError::Tensor { path, name, detail } => {
                write!(f, "{path}: tensor `{}`: {}", escaped(name), escaped(detail))
            }
        }
    }
}

impl std::error::Error for PlanError {}

/// The data of one stored tensor, as the compiler hands it to [`Plan::new`]: f32, or f16
/// for a variant's replacement stored at half precision.
#[derive(Clone, Debug)]
pub enum TensorData {
    F32(Arc<[f32]>),
    F16(Arc<[f16]>),
}

impl TensorData {
    /// Elements.
    pub fn len(&self) -> usize {
        match self {
            TensorData::F32(d) => d.len(),
            TensorData::F16(d) => d.len(),
        }
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The element type.
    pub fn dtype(&self) -> DType {
        match self {
            TensorData::F32(_) => DType::F32,
            TensorData::F16(_) => DType::F16,
        }
    }
}

impl From<Arc<[f32]>> for TensorData {
    fn from(d: Arc<[f32]>) -> TensorData {
        TensorData::F32(d)
    }
}

impl From<Vec<f32>> for TensorData {
    fn from(d: Vec<f32>) -> TensorData {
        TensorData::F32(d.into())
    }
}

impl From<Vec<f16>> for TensorData {
    fn from(d: Vec<f16>) -> TensorData {
        TensorData::F16(d.into())
    }
}

/// Where the tensor bytes are.
enum Weights {
    /// Straight from the compiler.
    Owned(Vec<TensorData>),
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
    /// Records the plan's footprint at batch 1 on one thread in
    /// [`Manifest::footprint`] (`None` if it does not fit in memory at all).
    pub fn new<T: Into<TensorData>>(manifest: Manifest, tensors: Vec<T>) -> Result<Plan, PlanError> {
        let tensors = tensors.into_iter().map(Into::into).collect();
        let mut plan = Plan::build(manifest, Weights::Owned(tensors), "<compiled plan>")?;
        plan.manifest.footprint = crate::exec::compiled_footprint(&plan);
        Ok(plan)
    }

    /// Validates and builds the variant maps.
    fn build(manifest: Manifest, weights: Weights, path: &str) -> Result<Plan, PlanError> {
        let mut plan = Plan { manifest, weights, variants: VariantMaps::default() };
        plan.validate(path)?;
        let mut variants = VariantMaps::build(&plan.manifest);
        variants.mark_zeros(&plan.manifest, |t| plan.tensor(t).iter().all(|&v| v == 0.0));
        variants.mark_half(&plan.manifest);
        plan.variants = variants;
        Ok(plan)
    }

    /// The data of stored tensor `i`, an f32 tensor; empty for an f16 one (a variant's
    /// replacement, which a session reads decoded: [`Plan::tensor_f16`]).
    pub fn tensor(&self, i: usize) -> &[f32] {
        if self.manifest.tensors[i].dtype != DType::F32 {
            return &[];
        }
        self.f32_data(i)
    }

    /// The data of stored tensor `i`, which the caller knows to be f32 (a variant map's
    /// f16 flags, [`VariantTensors::get`]): no second look at the manifest.
    fn f32_data(&self, i: usize) -> &[f32] {
        match &self.weights {
            Weights::Owned(t) => match &t[i] {
                TensorData::F32(d) => d,
                TensorData::F16(_) => &[],
            },
            // Alignment and length were checked at load.
            Weights::Mapped { map, ranges } => bytemuck::cast_slice(&map[ranges[i].clone()]),
        }
    }

    /// The data of stored tensor `i` if it is f16 (a variant's replacement stored at half
    /// precision), else `None`.
    pub fn tensor_f16(&self, i: usize) -> Option<&[f16]> {
        if self.manifest.tensors[i].dtype != DType::F16 {
            return None;
        }
        match &self.weights {
            Weights::Owned(t) => match &t[i] {
                TensorData::F16(d) => Some(d),
                TensorData::F32(_) => None,
            },
            Weights::Mapped { map, ranges } => Some(bytemuck::cast_slice(&map[ranges[i].clone()])),
        }
    }

    /// The stored bytes of tensor `i`, as the file holds them.
    fn tensor_raw(&self, i: usize) -> &[u8] {
        match &self.weights {
            Weights::Owned(t) => match &t[i] {
                TensorData::F32(d) => bytemuck::cast_slice(d),
                TensorData::F16(d) => bytemuck::cast_slice(d),
            },
            Weights::Mapped { map, ranges } => &map[ranges[i].clone()],
        }
    }

    /// Whether the weights are borrowed from a mapped file.
    pub fn is_mapped(&self) -> bool {
        matches!(self.weights, Weights::Mapped { .. })
    }

    /// Total bytes of the stored tensors.
    pub fn tensor_bytes(&self) -> usize {
        self.manifest.tensors.iter().map(TensorSpec::bytes).sum()
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
        let data: Vec<&[u8]> = (0..self.manifest.tensors.len()).map(|i| self.tensor_raw(i)).collect();
        let checksum = Plan::checksum(&json, data.iter());
        let mut views = Vec::with_capacity(data.len());
        for (spec, bytes) in self.manifest.tensors.iter().zip(&data) {
            let dtype = if spec.dtype == DType::F16 { Dtype::F16 } else { Dtype::F32 };
            let view = TensorView::new(dtype, spec.shape.clone(), bytes).map_err(|e| PlanError::Tensor {
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

    /// Maps a plan file and checks it. The weights stay in the mapping. The file must be
    /// a regular file of at most [`MAX_PLAN_BYTES`].
    pub fn load(path: &Path) -> Result<Plan, PlanError> {
        let name = path.display().to_string();
        let file = std::fs::File::open(path).map_err(|error| PlanError::Io { path: name.clone(), error })?;
        // Of the opened file, so that it cannot be swapped between the check and the map.
        let meta = file.metadata().map_err(|error| PlanError::Io { path: name.clone(), error })?;
        if !meta.is_file() {
            return Err(PlanError::NotAFile { path: name, detail: "not a regular file".into() });
        }
        if meta.len() > MAX_PLAN_BYTES {
            let detail = format!("{} bytes, more than the {MAX_PLAN_BYTES} a plan may have", meta.len());
            return Err(PlanError::NotAFile { path: name, detail });
        }
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
        let meta_version: Option<u32> = version.trim().parse().ok();
        if !readable_version(meta_version) {
            return Err(PlanError::Version { path: path.into(), found: version.clone() });
        }
        let json = get(KEY_MANIFEST)?;
        let stored = get(KEY_CHECKSUM)?;
        // serde's message may quote the text it could not read: escaped like a name.
        let manifest: Manifest = serde_json::from_str(json)
            .map_err(|e| PlanError::Manifest { path: path.into(), detail: escaped(&e.to_string()).into_owned() })?;
        // The manifest's version is the container's (a flipped bit turns "3" into "2").
        if !readable_version(Some(manifest.format_version)) || meta_version != Some(manifest.format_version) {
            return Err(PlanError::Version { path: path.into(), found: manifest.format_version.to_string() });
        }
        let data_start = 8 + header_len;
        let base = map.as_ptr() as usize;
        let mut ranges = Vec::with_capacity(manifest.tensors.len());
        for spec in &manifest.tensors {
            let terr = |detail: String| PlanError::Tensor { path: path.into(), name: spec.name.clone(), detail };
            let view = st.tensor(&spec.name).map_err(|e| terr(e.to_string()))?;
            // The manifest's type (validation: f32, or f16 for a replacement).
            let (want, align) = match spec.dtype {
                DType::F16 => (Dtype::F16, 2),
                _ => (Dtype::F32, 4),
            };
            if view.dtype() != want {
                return Err(terr(format!("stored as {:?}, the manifest says {:?}", view.dtype(), want)));
            }
            if view.shape() != spec.shape.as_slice() {
                return Err(terr(format!(
                    "stored shape {:?} differs from the manifest's {:?}",
                    view.shape(),
                    spec.shape
                )));
            }
            let start = view.data().as_ptr() as usize - base;
            if start < data_start || !(base + start).is_multiple_of(align) {
                return Err(terr(format!("is not {align}-byte aligned in the file")));
            }
            ranges.push(start..start + view.data().len());
        }
        let computed = Plan::checksum(json, ranges.iter().map(|r| &map[r.clone()]));
        // The text the writer wrote, exactly: parsed as a number, a flipped case bit
        // (`d` to `D`) or a digit flipped to a space would pass.
        if *stored != format!("{computed:08x}") {
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
                if data.dtype() != spec.dtype {
                    return bad(format!(
                        "tensor `{}` is {} data, the manifest says {}",
                        spec.name,
                        data.dtype().as_str(),
                        spec.dtype.as_str()
                    ));
                }
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
