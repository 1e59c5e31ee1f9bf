//! Reading and writing tensors for `readi run`: `.npy` (NumPy) and `.safetensors`, and
//! outputs as `.json` for tools that read no tensor format (a detector's boxes and scores).

use std::collections::HashMap;
use std::path::Path;

use ndarray::{ArrayD, IxDyn};
use ndarray_npy::{ReadNpyExt, WriteNpyExt};
use readi_plan::DType;
use readi_runtime::exec::Tensor;
use readi_runtime::plan::escaped;
use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use super::files;

/// A tensor read from a file: f32 data and shape.
pub type Loaded = (Vec<usize>, Vec<f32>);

fn extension(path: &Path) -> String {
    path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase()
}

/// [`files::check_file`] for inputs and samples, whose limit is `--max-memory`.
pub fn check_file(path: &Path, limit: usize) -> Result<u64, String> {
    files::check_file(path, limit as u64).map_err(|e| format!("{e} (--max-memory)"))
}

/// [`files::read_bounded`] for inputs and samples, whose limit is `--max-memory`.
pub fn read_limited(path: &Path, limit: usize) -> Result<Vec<u8>, String> {
    files::read_bounded(path, limit as u64).map_err(|e| format!("{e} (--max-memory)"))
}

/// The shape and data bytes a `.npy` header declares and the bytes the file holds after
/// the header, when the header can be read (`None`: the reader reports what is wrong).
fn npy_sizes(path: &Path, file_len: u64) -> Option<(Vec<usize>, u64, u64)> {
    use std::io::Read;
    let mut f = std::fs::File::open(path).ok()?;
    let mut head = [0u8; 12];
    f.read_exact(&mut head[..10]).ok()?;
    if &head[..6] != b"\x93NUMPY" {
        return None;
    }
    let (len, prefix) = match head[6] {
        1 => (u16::from_le_bytes([head[8], head[9]]) as u64, 10),
        2 | 3 => {
            f.read_exact(&mut head[10..12]).ok()?;
            (u32::from_le_bytes([head[8], head[9], head[10], head[11]]) as u64, 12)
        }
        _ => return None,
    };
    if len > 1 << 20 || prefix + len > file_len {
        return None;
    }
    let mut header = vec![0u8; len as usize];
    f.read_exact(&mut header).ok()?;
    let header = String::from_utf8(header).ok()?;
    let descr = header.split("'descr'").nth(1)?.split('\'').nth(1)?;
    let item: u64 = descr.get(2..)?.parse().ok()?;
    let shape_text = header.split("'shape'").nth(1)?.split('(').nth(1)?.split(')').next()?;
    let shape: Option<Vec<usize>> =
        shape_text.split(',').map(str::trim).filter(|d| !d.is_empty()).map(|d| d.parse().ok()).collect();
    let shape = shape?;
    let want = shape.iter().try_fold(item, |a, &d| a.checked_mul(d as u64))?;
    Some((shape, want, file_len - prefix - len))
}

/// Reads the tensor for input `name` from a `.npy` file, or from a `.safetensors` file
/// (the tensor called `name`, or its only tensor), a regular file of at most `limit`
/// bytes. f64, f16 and bf16 are converted.
pub fn read_input(name: &str, path: &Path, limit: usize) -> Result<Loaded, String> {
    let shown = path.display();
    match extension(path).as_str() {
        "npy" => {
            let len = check_file(path, limit)?;
            if let Some((shape, want, have)) = npy_sizes(path, len)
                && have < want
            {
                return Err(format!(
                    "{shown}: truncated .npy file: its header declares shape {shape:?}, {want} bytes of data, \
                     but the file holds {have}"
                ));
            }
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
            let bytes = read_limited(path, limit)?;
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
        _ => Err(format!("{shown}: inputs are read from .npy, .safetensors or (point clouds) .bin files")),
    }
}

/// Whether `path` is a KITTI / nuScenes point cloud (`.bin`), read by [`read_bin`].
pub fn is_bin(path: &Path) -> bool {
    extension(path) == "bin"
}

/// Reads a KITTI / nuScenes `.bin` point cloud: raw little-endian f32 rows of `columns`
/// values (4: x, y, z, intensity; 5 adds nuScenes' ring index), a regular file of at
/// most `limit` bytes. A size that is not a whole number of rows is refused.
pub fn read_bin(path: &Path, columns: usize, limit: usize) -> Result<Loaded, String> {
    let shown = path.display();
    let bytes = read_limited(path, limit)?;
    let row = columns.max(1) * 4;
    if bytes.is_empty() || bytes.len() % row != 0 {
        return Err(format!(
            "{shown}: a .bin point cloud holds rows of {columns} little-endian f32 values ({row} bytes), \
             but the file has {} bytes, not a positive multiple of {row}",
            bytes.len()
        ));
    }
    let data: Vec<f32> = bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect();
    Ok((vec![data.len() / columns.max(1), columns], data))
}

/// Writes outputs, each of the element type the model gives it (`dtypes[i]` for
/// `outputs[i]`: an i64 or bool output is f32 holding integers, written as int64 or bool):
/// all of them to one `.safetensors` or `.json` file, or one to a `.npy` file.
pub fn write_outputs(path: &Path, outputs: &[(String, Tensor)], dtypes: &[DType]) -> Result<(), String> {
    let named: Vec<(&str, &Tensor)> = outputs.iter().map(|(n, t)| (n.as_str(), t)).collect();
    write_named(path, &named, dtypes)
}

/// [`write_outputs`] on borrowed names and tensors.
fn write_named(path: &Path, outputs: &[(&str, &Tensor)], dtypes: &[DType]) -> Result<(), String> {
    let shown = path.display();
    let dtype = |i: usize| dtypes.get(i).copied().unwrap_or(DType::F32);
    match extension(path).as_str() {
        "json" => write_json(path, outputs, dtypes),
        "npy" => {
            let [(_, t)] = outputs else {
                let names: Vec<String> = outputs.iter().map(|(n, _)| escaped(n).into_owned()).collect();
                return Err(format!(
                    "the model has {} outputs ({}); write them to a .safetensors or .json file, or pick one with --output NAME={shown}",
                    outputs.len(),
                    names.join(", ")
                ));
            };
            write_npy(path, t, dtype(0))
        }
        "safetensors" => {
            let encoded: Vec<(Dtype, Vec<u8>)> =
                outputs.iter().enumerate().map(|(i, (_, t))| encode(&t.data, dtype(i))).collect();
            let mut views = Vec::new();
            for ((name, t), (d, b)) in outputs.iter().zip(&encoded) {
                let view = TensorView::new(*d, t.shape.clone(), b).map_err(|e| format!("{}: {e}", escaped(name)))?;
                views.push((name.to_string(), view));
            }
            let data = safetensors::serialize(views, None::<HashMap<String, String>>).map_err(|e| e.to_string())?;
            std::fs::write(path, data).map_err(|e| format!("cannot write {shown}: {e}"))
        }
        _ => Err(format!("{shown}: outputs are written to .npy, .safetensors or .json files")),
    }
}

/// The name of the element type an output is written as (`f32`, `i64`, `bool`): what
/// [`encode`] and [`write_npy`] write it as.
fn written_dtype(dtype: DType) -> &'static str {
    match dtype {
        DType::I64 | DType::I32 => "i64",
        DType::Bool => "bool",
        _ => "f32",
    }
}

/// The outputs as one JSON object, `{"name": {"dtype", "shape", "data"}}` in output order,
/// `data` flat in row-major order, streamed (no copy of the data).
struct JsonOutputs<'a>(&'a [(&'a str, &'a Tensor)], &'a [DType]);

/// One output's values: integers as integers, bools as `true` / `false`, floats in their
/// shortest round-trip form (serde_json's f32 writer), NaN and infinities as `null`.
struct JsonData<'a>(&'a [f32], DType);

#[derive(serde::Serialize)]
struct JsonTensor<'a> {
    dtype: &'static str,
    shape: &'a [usize],
    data: JsonData<'a>,
}

impl serde::Serialize for JsonOutputs<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        let mut map = s.serialize_map(Some(self.0.len()))?;
        for (i, (name, t)) in self.0.iter().enumerate() {
            let dtype = self.1.get(i).copied().unwrap_or(DType::F32);
            let data = JsonData(&t.data, dtype);
            map.serialize_entry(name, &JsonTensor { dtype: written_dtype(dtype), shape: &t.shape, data })?;
        }
        map.end()
    }
}

impl serde::Serialize for JsonData<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeSeq;
        let mut seq = s.serialize_seq(Some(self.0.len()))?;
        for &v in self.0 {
            match self.1 {
                DType::I64 | DType::I32 => seq.serialize_element(&(v as i64))?,
                DType::Bool => seq.serialize_element(&(v != 0.0))?,
                _ => seq.serialize_element(&v)?,
            }
        }
        seq.end()
    }
}

/// Writes outputs to a `.json` file as [`JsonOutputs`] lays them out, one line.
fn write_json(path: &Path, outputs: &[(&str, &Tensor)], dtypes: &[DType]) -> Result<(), String> {
    use std::io::Write;
    let shown = path.display();
    let file = std::fs::File::create(path).map_err(|e| format!("cannot write {shown}: {e}"))?;
    let mut w = std::io::BufWriter::new(file);
    serde_json::to_writer(&mut w, &JsonOutputs(outputs, dtypes)).map_err(|e| format!("cannot write {shown}: {e}"))?;
    w.write_all(b"\n").and_then(|()| w.flush()).map_err(|e| format!("cannot write {shown}: {e}"))
}

/// Writes output `name` alone (`--output NAME=FILE`): as `.npy`, or as a `.json` or
/// `.safetensors` file holding only it.
pub fn write_one(path: &Path, name: &str, t: &Tensor, dtype: DType) -> Result<(), String> {
    match extension(path).as_str() {
        "json" | "safetensors" => write_named(path, &[(name, t)], &[dtype]),
        _ => write_npy(path, t, dtype),
    }
}

/// The safetensors element type and little-endian bytes of values of type `dtype`.
fn encode(data: &[f32], dtype: DType) -> (Dtype, Vec<u8>) {
    match dtype {
        DType::I64 | DType::I32 => (Dtype::I64, data.iter().flat_map(|&v| (v as i64).to_le_bytes()).collect()),
        DType::Bool => (Dtype::BOOL, data.iter().map(|&v| u8::from(v != 0.0)).collect()),
        _ => (Dtype::F32, data.iter().flat_map(|v| v.to_le_bytes()).collect()),
    }
}

/// Writes one tensor as `.npy`, of the element type `dtype` (int64 for i64, bool for
/// bool, else float32).
pub fn write_npy(path: &Path, t: &Tensor, dtype: DType) -> Result<(), String> {
    let shown = path.display();
    let file = std::fs::File::create(path).map_err(|e| format!("cannot write {shown}: {e}"))?;
    let w = std::io::BufWriter::new(file);
    let shape = IxDyn(&t.shape);
    let err = |e: ndarray::ShapeError| format!("{shown}: {e}");
    let written = match dtype {
        DType::I64 | DType::I32 => {
            ArrayD::from_shape_vec(shape, t.data.iter().map(|&v| v as i64).collect()).map_err(err)?.write_npy(w)
        }
        DType::Bool => {
            ArrayD::from_shape_vec(shape, t.data.iter().map(|&v| v != 0.0).collect()).map_err(err)?.write_npy(w)
        }
        _ => ArrayD::from_shape_vec(shape, t.data.clone()).map_err(err)?.write_npy(w),
    };
    written.map_err(|e| format!("cannot write {shown}: {e}"))
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
        write_npy(&npy, &t, DType::F32).expect("write npy");
        assert_eq!(read_input("x", &npy, 1 << 20).expect("read npy"), (t.shape.clone(), t.data.clone()));
        let st = dir.join("out.safetensors");
        write_outputs(&st, &[("y".into(), t.clone()), ("z".into(), t.clone())], &[]).expect("write safetensors");
        assert_eq!(read_input("z", &st, 1 << 20).expect("read by name"), (t.shape.clone(), t.data.clone()));
        assert!(read_input("w", &st, 1 << 20).expect_err("no such tensor").contains("has no tensor `w`"));
        let bin = dir.join("sweep.bin");
        let pts: Vec<u8> =
            [1.0f32, 2.0, 3.0, 0.5, -1.0, -2.0, -3.0, 0.25].iter().flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(&bin, &pts).expect("write bin");
        assert_eq!(
            read_bin(&bin, 4, 1 << 20).expect("4 columns"),
            (vec![2, 4], vec![1.0, 2.0, 3.0, 0.5, -1.0, -2.0, -3.0, 0.25])
        );
        let e = read_bin(&bin, 5, 1 << 20).expect_err("32 bytes are not rows of 5");
        assert!(e.contains("sweep.bin") && e.contains("not a positive multiple of 20"), "{e}");
        // Truncated: the header is intact, the data short.
        let bytes = std::fs::read(&npy).expect("read back");
        let cut = dir.join("cut.npy");
        std::fs::write(&cut, &bytes[..bytes.len() - 5]).expect("write");
        let err = read_input("x", &cut, 1 << 20).expect_err("truncated");
        assert!(
            err.contains("cut.npy: truncated .npy file") && err.contains("24 bytes of data, but the file holds 19"),
            "{err}"
        );
        assert!(
            read_input("x", &npy, 16)
                .expect_err("over the limit")
                .contains("over the limit of 16 bytes for this kind of file (--max-memory)")
        );
        // Integer and bool outputs are written as int64 and bool.
        let i = Tensor { shape: vec![3], data: vec![4.0, 0.0, 191.0] };
        let b = Tensor { shape: vec![2], data: vec![1.0, 0.0] };
        let npy = dir.join("i.npy");
        write_npy(&npy, &i, DType::I64).expect("write i64 npy");
        let a = ArrayD::<i64>::read_npy(std::fs::File::open(&npy).expect("open")).expect("an int64 .npy");
        assert_eq!(a.iter().copied().collect::<Vec<_>>(), [4, 0, 191]);
        write_npy(&npy, &b, DType::Bool).expect("write bool npy");
        let a = ArrayD::<bool>::read_npy(std::fs::File::open(&npy).expect("open")).expect("a bool .npy");
        assert_eq!(a.iter().copied().collect::<Vec<_>>(), [true, false]);
        write_outputs(&st, &[("i".into(), i), ("b".into(), b)], &[DType::I64, DType::Bool]).expect("write");
        let bytes = std::fs::read(&st).expect("read back");
        let st = SafeTensors::deserialize(&bytes).expect("safetensors");
        let iv = st.tensor("i").expect("i");
        assert_eq!((iv.dtype(), iv.data()), (Dtype::I64, &[4i64, 0, 191].map(i64::to_le_bytes).concat()[..]));
        let bv = st.tensor("b").expect("b");
        assert_eq!((bv.dtype(), bv.data()), (Dtype::BOOL, &[1u8, 0][..]));
        // JSON: integers as integers, bools as bools, floats shortest, NaN and inf null.
        let i = Tensor { shape: vec![3], data: vec![4.0, -1.0, 191.0] };
        let b = Tensor { shape: vec![1, 2], data: vec![1.0, 0.0] };
        let f = Tensor { shape: vec![2, 3], data: vec![0.1, -2.5, 1e20, f32::NAN, f32::INFINITY, 16777216.0] };
        let json = dir.join("out.json");
        let outputs = [("idx".into(), i.clone()), ("mask".into(), b), ("box \"0\"".into(), f)];
        write_outputs(&json, &outputs, &[DType::I64, DType::Bool]).expect("write json");
        assert_eq!(
            std::fs::read_to_string(&json).expect("read back"),
            concat!(
                r#"{"idx":{"dtype":"i64","shape":[3],"data":[4,-1,191]},"#,
                r#""mask":{"dtype":"bool","shape":[1,2],"data":[true,false]},"#,
                r#""box \"0\"":{"dtype":"f32","shape":[2,3],"data":[0.1,-2.5,1e+20,null,null,16777216.0]}}"#,
                "\n"
            )
        );
        write_one(&json, "idx", &i, DType::I64).expect("write one");
        assert_eq!(
            std::fs::read_to_string(&json).expect("read back"),
            "{\"idx\":{\"dtype\":\"i64\",\"shape\":[3],\"data\":[4,-1,191]}}\n"
        );
        // `NAME=FILE.safetensors`: a safetensors file of that output alone, not .npy bytes.
        let one = dir.join("one.safetensors");
        write_one(&one, "idx", &i, DType::I64).expect("write one");
        let bytes = std::fs::read(&one).expect("read back");
        let st = SafeTensors::deserialize(&bytes).expect("a safetensors file");
        assert_eq!((st.names(), st.tensor("idx").expect("idx").dtype()), (vec!["idx"], Dtype::I64));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
