//! Data movement without arithmetic, with PyTorch's semantics: `pad` (constant, reflect,
//! replicate; `torch.nn.functional.pad`), `roll` (`torch.roll`) and `slice` (Python's
//! `x[a:b:s, i, ...]`, which also writes `narrow`, `select`, `chunk` and `split`) and
//! `expand` (`Tensor.expand`).
//!
//! Bounds are kept as the source wrote them (negative counts from the end) and resolved
//! against the real sizes by [`SliceAxis::resolve`], so a slice of a symbolic batch axis
//! that keeps it whole (`x[:, 0:64]`) stays symbolic.

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, float, list};
use crate::dim::Dim;

/// How `pad` fills the border.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum PadMode {
    /// The value `value`.
    Constant,
    /// The mirror image without the edge element (`[a b c]` left by 2: `c b a b c`).
    Reflect,
    /// The edge element repeated.
    Replicate,
}

impl PadMode {
    pub fn name(self) -> &'static str {
        match self {
            PadMode::Constant => "constant",
            PadMode::Reflect => "reflect",
            PadMode::Replicate => "replicate",
        }
    }
    pub fn parse(s: &str) -> Option<PadMode> {
        [PadMode::Constant, PadMode::Reflect, PadMode::Replicate].into_iter().find(|m| m.name() == s)
    }
}

/// `torch.nn.functional.pad(x, pad, mode, value)`: `pad` holds pairs `(before, after)`
/// from the last axis backwards (`[left, right, top, bottom]` pads W then H of NCHW). A
/// negative amount crops.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pad {
    pub pads: Vec<i64>,
    pub mode: PadMode,
    pub value: f64,
}

impl Pad {
    /// `(before, after)` for every axis of a rank-`rank` tensor, first axis first.
    pub fn per_axis(&self, rank: usize) -> Vec<(i64, i64)> {
        let mut out = vec![(0, 0); rank];
        for (k, p) in self.pads.chunks(2).enumerate() {
            if k < rank {
                out[rank - 1 - k] = (p[0], p.get(1).copied().unwrap_or(0));
            }
        }
        out
    }
}

impl Operator for Pad {
    fn kind_name(&self) -> &'static str {
        "pad"
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = inputs[0];
        let n = self.pads.len();
        if !n.is_multiple_of(2) || n > 2 * x.rank() {
            return Err(ShapeError::new(format!(
                "pad needs pairs for at most the {} axes of {x}, got {n} amounts {}",
                x.rank(),
                list(&self.pads)
            )));
        }
        let mut shape = x.shape.clone();
        for (axis, (l, r)) in self.per_axis(x.rank()).into_iter().enumerate() {
            if l == 0 && r == 0 {
                continue;
            }
            let Some(d) = x.known_dim(axis) else {
                return Err(ShapeError::new(format!("pad of axis {axis} of {x} needs its size known")));
            };
            if self.mode == PadMode::Reflect && (l >= d || r >= d) {
                return Err(ShapeError::new(format!(
                    "reflect pad ({l}, {r}) of axis {axis} of {x} must be less than its size {d}"
                )));
            }
            if self.mode == PadMode::Replicate && d == 0 {
                return Err(ShapeError::new(format!("replicate pad of the empty axis {axis} of {x}")));
            }
            let out = d.checked_add(l).and_then(|v| v.checked_add(r)).unwrap_or(-1);
            if out < 0 {
                return Err(ShapeError::new(format!("pad ({l}, {r}) of axis {axis} of {x} leaves a negative size")));
            }
            shape[axis] = Dim::known(out);
        }
        Ok(TensorType::new(x.dtype, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let mut a = vec![("pad", list(&self.pads)), ("mode", self.mode.name().to_string())];
        if self.mode == PadMode::Constant {
            a.push(("value", float(self.value)));
        }
        a
    }
}

/// `torch.roll(x, shifts, dims)`: element `i` along each axis in `axes` moves to
/// `i + shift` modulo the size. With no axes the tensor is rolled as if flattened (one
/// shift). An axis listed twice rolls by the sum.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Roll {
    pub shifts: Vec<i64>,
    pub axes: Vec<usize>,
}

impl Operator for Roll {
    fn kind_name(&self) -> &'static str {
        "roll"
    }

    /// A copy: integer and bool tensors move like floats (indices from `topk`).
    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = inputs[0];
        if self.axes.is_empty() {
            if self.shifts.len() != 1 {
                return Err(ShapeError::new(format!("roll without dims takes one shift, got {}", list(&self.shifts))));
            }
        } else if self.shifts.len() != self.axes.len() {
            return Err(ShapeError::new(format!("roll has {} shifts for {} dims", self.shifts.len(), self.axes.len())));
        }
        for &a in &self.axes {
            super::axis_in_range(a, x)?;
        }
        Ok(x.clone())
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("shifts", list(&self.shifts)), ("dims", list(&self.axes))]
    }
}

/// What `slice` does to one input axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum SliceAxis {
    /// `start:stop:step` with Python's rules: negative bounds count from the end, bounds
    /// past either end are clamped, `None` is the end in the step's direction. `step >= 1`.
    Range { start: Option<i64>, stop: Option<i64>, step: i64 },
    /// One index (negative counts from the end): the axis is removed.
    Index(i64),
}

/// A resolved [`SliceAxis`] on an axis of known size: the first index, the count, the
/// step, and whether the axis is kept.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Resolved {
    pub start: usize,
    pub len: usize,
    pub step: usize,
    pub keep: bool,
}

impl SliceAxis {
    /// The whole axis, `:`.
    pub const FULL: SliceAxis = SliceAxis::Range { start: None, stop: None, step: 1 };

    /// Resolves against an axis of size `d`; an error for an index out of range or a step
    /// below 1.
    pub fn resolve(self, d: i64) -> Result<Resolved, String> {
        match self {
            SliceAxis::Index(i) => {
                let j = if i < 0 { i + d } else { i };
                if j < 0 || j >= d {
                    return Err(format!("index {i} is out of range for an axis of size {d}"));
                }
                Ok(Resolved { start: j as usize, len: 1, step: 1, keep: false })
            }
            SliceAxis::Range { start, stop, step } => {
                if step < 1 {
                    return Err(format!("slice step must be at least 1, got {step}"));
                }
                let clamp = |v: Option<i64>, default: i64| match v {
                    None => default,
                    Some(v) if v < 0 => (v + d).max(0),
                    Some(v) => v.min(d),
                };
                let (a, b) = (clamp(start, 0), clamp(stop, d));
                let len = if b > a { (b - a - 1) / step + 1 } else { 0 };
                Ok(Resolved { start: a.min(d) as usize, len: len as usize, step: step as usize, keep: true })
            }
        }
    }

    fn is_full(self) -> bool {
        matches!(self, SliceAxis::Range { start: None | Some(0), stop: None, step: 1 })
    }
}

impl std::fmt::Display for SliceAxis {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            SliceAxis::Index(i) => write!(f, "{i}"),
            SliceAxis::Range { start, stop, step } => {
                if let Some(s) = start {
                    write!(f, "{s}")?;
                }
                f.write_str(":")?;
                if let Some(s) = stop {
                    write!(f, "{s}")?;
                }
                if step != 1 {
                    write!(f, ":{step}")?;
                }
                Ok(())
            }
        }
    }
}

/// `x[items]` in Python's basic indexing: one [`SliceAxis`] per input axis, first axis
/// first (the compiler fills the axes the source left out with `:`). The output has the
/// kept axes in order.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Slice {
    pub axes: Vec<SliceAxis>,
}

impl Slice {
    /// Every axis resolved against known sizes.
    pub fn resolve(&self, shape: &[usize]) -> Result<Vec<Resolved>, String> {
        if shape.len() != self.axes.len() {
            return Err(format!("slice of {} axes applied to a rank-{} tensor", self.axes.len(), shape.len()));
        }
        self.axes.iter().zip(shape).map(|(a, &d)| a.resolve(d as i64)).collect()
    }
}

impl Operator for Slice {
    fn kind_name(&self) -> &'static str {
        "slice"
    }

    /// A copy: integer and bool tensors move like floats (indices from `topk`).
    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = inputs[0];
        if self.axes.len() != x.rank() {
            return Err(ShapeError::new(format!(
                "slice {} has {} entries but {x} has {} axes",
                list(&self.axes),
                self.axes.len(),
                x.rank()
            )));
        }
        let mut shape = Vec::new();
        for (axis, (a, d)) in self.axes.iter().zip(&x.shape).enumerate() {
            match (a, d.as_known()) {
                (SliceAxis::Range { step, .. }, _) if *step < 1 => {
                    return Err(ShapeError::new(format!("slice step must be at least 1, got {step}")));
                }
                (a, _) if a.is_full() => shape.push(d.clone()),
                (SliceAxis::Index(_), None) => {}
                (a, Some(n)) => {
                    let r = a.resolve(n).map_err(|e| ShapeError::new(format!("axis {axis} of {x}: {e}")))?;
                    if r.keep {
                        shape.push(Dim::known(r.len as i64));
                    }
                }
                (a, None) => {
                    return Err(ShapeError::new(format!(
                        "slice `{a}` of the symbolic axis {axis} of {x} has no known size (only `:` keeps one)"
                    )));
                }
            }
        }
        Ok(TensorType::new(x.dtype, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("index", list(&self.axes))]
    }
}

/// `x.expand(sizes)` with the sizes resolved: `x` broadcast to `shape` (axes of size 1
/// repeated, new leading axes added), each output element a copy of its source.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Expand {
    pub shape: Vec<Dim>,
}

impl Operator for Expand {
    fn kind_name(&self) -> &'static str {
        "expand"
    }

    /// A copy: integer and bool tensors move like floats (indices from `topk`).
    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = inputs[0];
        let to = crate::dim::show_shape(&self.shape);
        if self.shape.len() < x.rank() {
            return Err(ShapeError::new(format!("cannot expand {x} to {to}, which has fewer axes")));
        }
        let lead = self.shape.len() - x.rank();
        for (i, d) in x.shape.iter().enumerate() {
            let want = &self.shape[lead + i];
            if d != want && d.as_known() != Some(1) {
                return Err(ShapeError::new(format!(
                    "cannot expand {x} to {to}: axis {i} has size {d}, neither 1 nor {want}"
                )));
            }
        }
        Ok(TensorType::new(x.dtype, self.shape.clone()))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("shape", list(&self.shape))]
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;
    use crate::ops::DType;

    fn pad(pads: &[i64], mode: PadMode) -> Pad {
        Pad { pads: pads.to_vec(), mode, value: 0.0 }
    }

    #[test]
    fn pad_pairs_run_from_the_last_axis() {
        // W 5 + 1 + 2 = 8, H 4 + 3 + 0 = 7.
        assert_eq!(run(&pad(&[1, 2, 3, 0], PadMode::Constant), &[t(&[2, 3, 4, 5])]), Ok(t(&[2, 3, 7, 8])));
        // Negative amounts crop: 5 - 1 - 2 = 2.
        assert_eq!(run(&pad(&[-1, -2], PadMode::Constant), &[t(&[3, 5])]), Ok(t(&[3, 2])));
        assert_eq!(run(&pad(&[], PadMode::Constant), &[t(&[3, 5])]), Ok(t(&[3, 5])));
        assert_eq!(run(&pad(&[3, 3], PadMode::Replicate), &[t(&[1, 1])]), Ok(t(&[1, 7])));
    }

    #[test]
    fn pad_errors_name_the_shape() {
        let e = run(&pad(&[1, 2, 3], PadMode::Constant), &[t(&[3, 5])]).expect_err("odd count");
        assert!(e.message.contains("f32[3, 5]"), "{e}");
        assert!(run(&pad(&[1, 1, 1, 1, 1, 1], PadMode::Constant), &[t(&[3, 5])]).is_err());
        let e = run(&pad(&[5, 0], PadMode::Reflect), &[t(&[3, 5])]).expect_err("reflect too wide");
        assert!(e.message.contains("less than its size 5"), "{e}");
        assert_eq!(run(&pad(&[4, 4], PadMode::Reflect), &[t(&[3, 5])]), Ok(t(&[3, 13])));
        assert!(run(&pad(&[-3, -3], PadMode::Constant), &[t(&[3, 5])]).is_err());
        let x = TensorType::new(DType::F32, vec![Dim::symbol("N"), Dim::known(4)]);
        assert!(run(&pad(&[1, 1, 1, 1], PadMode::Constant), std::slice::from_ref(&x)).is_err());
        assert_eq!(run(&pad(&[1, 1], PadMode::Constant), &[x]).expect("ok").to_string(), "f32[N, 6]");
    }

    #[test]
    fn roll_keeps_the_shape_and_checks_dims() {
        let r = Roll { shifts: vec![1, -2], axes: vec![0, 2] };
        assert_eq!(run(&r, &[t(&[2, 3, 4])]), Ok(t(&[2, 3, 4])));
        assert!(run(&Roll { shifts: vec![1], axes: vec![3] }, &[t(&[2, 3, 4])]).is_err());
        assert!(run(&Roll { shifts: vec![1, 2], axes: vec![0] }, &[t(&[2, 3, 4])]).is_err());
        assert!(run(&Roll { shifts: vec![1, 2], axes: vec![] }, &[t(&[2, 3, 4])]).is_err());
        assert_eq!(run(&Roll { shifts: vec![7], axes: vec![] }, &[t(&[2, 3])]), Ok(t(&[2, 3])));
    }

    fn r(start: Option<i64>, stop: Option<i64>, step: i64) -> SliceAxis {
        SliceAxis::Range { start, stop, step }
    }

    #[test]
    fn slice_bounds_follow_python() {
        // Hand-derived from Python: len(range(10)[a:b:s]).
        let cases = [
            (r(Some(2), Some(7), 1), 2, 5),
            (r(None, None, 3), 0, 4),     // 0 3 6 9
            (r(Some(-3), None, 1), 7, 3), // 7 8 9
            (r(Some(-20), Some(3), 1), 0, 3),
            (r(Some(4), Some(100), 4), 4, 2), // 4 8
            (r(Some(8), Some(2), 1), 8, 0),
            (r(Some(12), None, 1), 10, 0),
            (r(None, Some(-1), 2), 0, 5), // 0 2 4 6 8
        ];
        for (a, start, len) in cases {
            let got = a.resolve(10).expect("resolves");
            assert_eq!((got.start, got.len), (start, len), "{a}");
        }
        assert_eq!(SliceAxis::Index(-1).resolve(10).expect("ok").start, 9);
        assert!(SliceAxis::Index(10).resolve(10).is_err());
        assert!(SliceAxis::Index(-11).resolve(10).is_err());
        assert!(r(None, None, 0).resolve(10).is_err());
    }

    #[test]
    fn expand_repeats_axes_of_one() {
        let e = |s: &[i64]| Expand { shape: s.iter().map(|&d| Dim::known(d)).collect() };
        assert_eq!(run(&e(&[2, 3, 4]), &[t(&[3, 1])]), Ok(t(&[2, 3, 4])));
        assert_eq!(run(&e(&[3, 4]), &[t(&[1, 4])]), Ok(t(&[3, 4])));
        let err = run(&e(&[3, 4]), &[t(&[2, 4])]).expect_err("2 is not 1");
        assert!(err.message.contains("f32[2, 4]") && err.message.contains("[3, 4]"), "{err}");
        assert!(run(&e(&[4]), &[t(&[1, 4])]).is_err());
    }

    #[test]
    fn slice_shapes() {
        let s = Slice { axes: vec![SliceAxis::FULL, r(Some(0), Some(2), 1), SliceAxis::Index(-1)] };
        assert_eq!(run(&s, &[t(&[4, 3, 5])]), Ok(t(&[4, 2])));
        assert_eq!(s.attrs()[0].1, "[:, 0:2, -1]");
        let n = TensorType::new(DType::F32, vec![Dim::symbol("N"), Dim::known(3), Dim::known(5)]);
        assert_eq!(run(&s, std::slice::from_ref(&n)).expect("ok").to_string(), "f32[N, 2]");
        let on_n = Slice { axes: vec![r(None, Some(2), 1), SliceAxis::FULL, SliceAxis::FULL] };
        assert!(run(&on_n, std::slice::from_ref(&n)).is_err());
        let select_n = Slice { axes: vec![SliceAxis::Index(0), SliceAxis::FULL, r(None, None, 2)] };
        assert_eq!(run(&select_n, &[n]).expect("ok").to_string(), "f32[3, 3]");
        let e = run(&Slice { axes: vec![SliceAxis::Index(4)] }, &[t(&[4])]).expect_err("out of range");
        assert!(e.message.contains("f32[4]") && e.message.contains("index 4"), "{e}");
        assert!(run(&Slice { axes: vec![SliceAxis::FULL] }, &[t(&[4, 2])]).is_err());
        assert!(run(&Slice { axes: vec![r(None, None, 0)] }, &[t(&[4])]).is_err());
    }
}
