//! Reading and writing tensors for `readi run`: `.npy` (NumPy) and `.safetensors`.

use std::collections::HashMap;
use std::path::Path;

use ndarray::{ArrayD, IxDyn};
use ndarray_npy::{ReadNpyExt, WriteNpyExt};
use readi_runtime::exec::Tensor;
use readi_runtime::plan::escaped;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};

/// A tensor read from a file: f32 data and shape.
pub type Loaded = (Vec<usize>, Vec<f32>);

fn extension(path: &Path) -> String {
    path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase()
}

/// Reads the tensor for input `name` from a `.npy` file, or from a `.safetensors` file
/// (the tensor called `name`, or its only tensor). f64, f16 and bf16 are converted.
pub fn read_input(name: &str, path: &Path) -> Result<Loaded, String> {
    let shown = path.display();
    match extension(path).as_str() {
        "npy" => {
            let file = || std::fs::File::open(path).map_err(|e| format!("cannot read {shown}: {e}"));
            if let Ok(a) = ArrayD::<f32>::read_npy(file()?) {
                return Ok((a.shape().to_vec(), a.iter().copied().collect()));
            }
            match ArrayD::<f64>::read_npy(file()?) {
                Ok(a) => Ok((a.shape().to_vec(), a.iter().map(|&v| v as f32).collect())),
                Err(e) => Err(format!("{shown}: not a float32 or float64 .npy array ({e})")),
            }
        }
        "safetensors" => {
            let bytes = std::fs::read(path).map_err(|e| format!("cannot read {shown}: {e}"))?;
            let st = SafeTensors::deserialize(&bytes).map_err(|e| format!("{shown}: not a safetensors file ({e})"))?;
            let names = st.names();
            let key = if names.contains(&name) {
                name.to_string()
            } else if names.len() == 1 {
                names[0].to_string()
            } else {
                let names: Vec<String> = names.iter().map(|n| escaped(n).into_owned()).collect();
                return Err(format!("{shown} has no tensor `{}` (it has: {})", escaped(name), names.join(", ")));
            };
            let view = st.tensor(&key).map_err(|e| format!("{shown}: {e}"))?;
            let data = view.data();
            let values: Vec<f32> = match view.dtype() {
                Dtype::F32 => data.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
                Dtype::F64 => data
                    .chunks_exact(8)
                    .map(|b| f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32)
                    .collect(),
                Dtype::F16 => data.chunks_exact(2).map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32()).collect(),
                Dtype::BF16 => data.chunks_exact(2).map(|b| half::bf16::from_le_bytes([b[0], b[1]]).to_f32()).collect(),
                other => {
                    return Err(format!("{shown}: tensor `{}` has dtype {other:?}; inputs are floats", escaped(&key)));
                }
            };
            Ok((view.shape().to_vec(), values))
        }
        _ => Err(format!("{shown}: inputs are read from .npy or .safetensors files")),
    }
}

/// Writes outputs: all of them to one `.safetensors` file, or one to a `.npy` file.
pub fn write_outputs(path: &Path, outputs: &[(String, Tensor)]) -> Result<(), String> {
    let shown = path.display();
    match extension(path).as_str() {
        "npy" => {
            let [(_, t)] = outputs else {
                let names: Vec<String> = outputs.iter().map(|(n, _)| escaped(n).into_owned()).collect();
                return Err(format!(
                    "the model has {} outputs ({}); write them to a .safetensors file, or pick one with --output NAME={shown}",
                    outputs.len(),
                    names.join(", ")
                ));
            };
            write_npy(path, t)
        }
        "safetensors" => {
            let bytes: Vec<Vec<u8>> =
                outputs.iter().map(|(_, t)| t.data.iter().flat_map(|v| v.to_le_bytes()).collect()).collect();
            let mut views = Vec::new();
            for ((name, t), b) in outputs.iter().zip(&bytes) {
                let view =
                    TensorView::new(Dtype::F32, t.shape.clone(), b).map_err(|e| format!("{}: {e}", escaped(name)))?;
                views.push((name.clone(), view));
            }
            let data = safetensors::serialize(views, None::<HashMap<String, String>>).map_err(|e| e.to_string())?;
            std::fs::write(path, data).map_err(|e| format!("cannot write {shown}: {e}"))
        }
        _ => Err(format!("{shown}: outputs are written to .npy or .safetensors files")),
    }
}

/// Writes one tensor as `.npy`.
pub fn write_npy(path: &Path, t: &Tensor) -> Result<(), String> {
    let shown = path.display();
    let a = ArrayD::from_shape_vec(IxDyn(&t.shape), t.data.clone()).map_err(|e| format!("{shown}: {e}"))?;
    let file = std::fs::File::create(path).map_err(|e| format!("cannot write {shown}: {e}"))?;
    a.write_npy(std::io::BufWriter::new(file)).map_err(|e| format!("cannot write {shown}: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_and_safetensors_round_trip() {
        let dir = std::env::temp_dir().join(format!("readi-io-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let t = Tensor { shape: vec![2, 3], data: vec![1.0, -2.0, 3.5, 0.0, 5.0, -6.25] };
        let npy = dir.join("x.npy");
        write_npy(&npy, &t).expect("write npy");
        assert_eq!(read_input("x", &npy).expect("read npy"), (t.shape.clone(), t.data.clone()));
        let st = dir.join("out.safetensors");
        write_outputs(&st, &[("y".into(), t.clone()), ("z".into(), t.clone())]).expect("write safetensors");
        assert_eq!(read_input("z", &st).expect("read by name"), (t.shape.clone(), t.data.clone()));
        assert!(read_input("w", &st).expect_err("no such tensor").contains("has no tensor `w`"));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
