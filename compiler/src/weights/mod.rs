//! What the back end binds: weight sets (tensors by PyTorch name, read from safetensors
//! files, f16 and bf16 converted to f32, and written back), PEFT adapters ([`peft`]),
//! variant sources and what the variants own ([`variants`]), and the tensor table the
//! back-end passes work on ([`tensors`]). `bind_weights` and `bind_variants` bind them to
//! the graph.

pub mod peft;
pub mod tensors;
pub mod variants;

pub use variants::VariantSource;

use std::collections::{BTreeMap, BTreeSet};

use readi_grammar::diag::{Code, Diagnostic, Diagnostics};
use safetensors::tensor::{Dtype, SafeTensors};

/// Tensors by name, as f32.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WeightSet {
    pub tensors: BTreeMap<String, (Vec<usize>, Vec<f32>)>,
    /// The tensors that are int64 in the file (index buffers), their values exact in f32
    /// (at most [`MAX_EXACT_INT`] in magnitude): only an integer `buffer` binds them.
    pub integer: BTreeSet<String>,
}

/// The largest magnitude of an integer tensor's values: every integer up to it is exact
/// as an f32, the type the compiler keeps every tensor in (an index into a table has far
/// fewer entries).
pub const MAX_EXACT_INT: i64 = 1 << 24;

/// A problem with a weights file as a whole (not tied to one layer).
fn file_error(file: &str, message: String) -> Diagnostic {
    Diagnostic::error(Code::Weights, format!("{file}: {message}"))
}

impl WeightSet {
    /// Parses safetensors bytes. Tensors of float types become f32; int64 tensors other
    /// than the `num_batches_tracked` counters (which are ignored) are kept as exact f32
    /// values and listed in `integer`, for the spec's integer buffers.
    pub fn from_safetensors(file: &str, bytes: &[u8]) -> Result<WeightSet, Diagnostics> {
        let st = SafeTensors::deserialize(bytes).map_err(|e| {
            Diagnostics(vec![file_error(file, format!("not a valid safetensors file ({e}); is it truncated?"))])
        })?;
        let mut set = WeightSet::default();
        let mut diags = Diagnostics::default();
        let mut names: Vec<String> = st.names().into_iter().map(String::from).collect();
        names.sort();
        for name in names {
            let Ok(view) = st.tensor(&name) else { continue };
            let shape = view.shape().to_vec();
            let data = view.data();
            let values: Vec<f32> = match view.dtype() {
                Dtype::F32 => data.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
                Dtype::F16 => data.chunks_exact(2).map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32()).collect(),
                Dtype::BF16 => data.chunks_exact(2).map(|b| half::bf16::from_le_bytes([b[0], b[1]]).to_f32()).collect(),
                Dtype::I64 if name.ends_with("num_batches_tracked") => continue,
                Dtype::I64 => {
                    let ints = data.chunks_exact(8).map(|b| i64::from_le_bytes(b.try_into().unwrap_or([0; 8])));
                    let mut values = Vec::with_capacity(data.len() / 8);
                    for (i, v) in ints.enumerate() {
                        if v.abs() > MAX_EXACT_INT {
                            diags.push(file_error(
                                file,
                                format!(
                                    "int64 tensor `{name}` holds {v} at flat index {i}; readi reads integer \
                                     tensors (index buffers) with values up to {MAX_EXACT_INT} in magnitude"
                                ),
                            ));
                            break;
                        }
                        values.push(v as f32);
                    }
                    set.integer.insert(name.clone());
                    values
                }
                other => {
                    diags.push(file_error(
                        file,
                        format!("tensor `{name}` has dtype {other:?}; readi reads F32, F16 and BF16 weights"),
                    ));
                    continue;
                }
            };
            set.tensors.insert(name, (shape, values));
        }
        if diags.has_errors() { Err(diags) } else { Ok(set) }
    }

    /// Removes `prefix` from the names that start with it, as PyTorch's
    /// `consume_prefix_in_state_dict_if_present` does for the `module.` a training wrapper
    /// adds; names without it are kept. Returns how many names changed. Two names that
    /// become one are an error naming both.
    pub fn strip_prefix(&mut self, file: &str, prefix: &str) -> Result<usize, Diagnostics> {
        let mut out = BTreeMap::new();
        let mut stripped = 0;
        let mut integer = BTreeSet::new();
        for (name, t) in std::mem::take(&mut self.tensors) {
            let new = match name.strip_prefix(prefix) {
                Some(rest) if !rest.is_empty() => {
                    stripped += 1;
                    rest.to_string()
                }
                _ => name.clone(),
            };
            if out.contains_key(&new) {
                return Err(Diagnostics(vec![file_error(
                    file,
                    format!("without the prefix `{prefix}`, tensor `{name}` has the name of another tensor, `{new}`"),
                )]));
            }
            if self.integer.remove(&name) {
                integer.insert(new.clone());
            }
            out.insert(new, t);
        }
        self.tensors = out;
        self.integer = integer;
        Ok(stripped)
    }

    /// The set as safetensors bytes (f32, the integer tensors int64), as PyTorch's
    /// `save_file(state_dict)` writes.
    pub fn to_safetensors(&self) -> Result<Vec<u8>, String> {
        use safetensors::tensor::TensorView;
        let bytes: Vec<(&String, &Vec<usize>, Vec<u8>)> = self
            .tensors
            .iter()
            .map(|(name, (shape, data))| {
                let b = if self.integer.contains(name) {
                    data.iter().flat_map(|&v| (v as i64).to_le_bytes()).collect()
                } else {
                    data.iter().flat_map(|v| v.to_le_bytes()).collect()
                };
                (name, shape, b)
            })
            .collect();
        let mut views = Vec::with_capacity(bytes.len());
        for (name, shape, b) in &bytes {
            let dtype = if self.integer.contains(*name) { Dtype::I64 } else { Dtype::F32 };
            let view = TensorView::new(dtype, (*shape).clone(), b).map_err(|e| format!("tensor `{name}`: {e}"))?;
            views.push(((*name).clone(), view));
        }
        safetensors::serialize(views, None).map_err(|e| e.to_string())
    }
}
