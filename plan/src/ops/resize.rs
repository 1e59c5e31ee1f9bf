//! `upsample`: resize of the last two axes of NCHW to a fixed size.

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, float, nchw};
use crate::dim::Dim;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum UpsampleMode {
    Nearest,
    Bilinear,
}

/// Resize of the last two axes to `size`. `scale` is the factor the source gave, which
/// PyTorch uses (rather than the size ratio) to map output to input positions.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Upsample {
    pub size: [i64; 2],
    pub scale: Option<[f64; 2]>,
    pub mode: UpsampleMode,
    pub align_corners: bool,
}

impl Operator for Upsample {
    fn kind_name(&self) -> &'static str {
        "upsample"
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = nchw(inputs[0], "upsample")?;
        let size = self.size;
        if size[0] < 1 || size[1] < 1 {
            return Err(ShapeError::new(format!("upsample to an empty size {}x{}", size[0], size[1])));
        }
        if self.scale.is_some_and(|s| !(s[0] > 0.0 && s[1] > 0.0 && s[0].is_finite() && s[1].is_finite())) {
            return Err(ShapeError::new("upsample scale must be positive and finite"));
        }
        let shape = vec![x.shape[0].clone(), x.shape[1].clone(), Dim::known(size[0]), Dim::known(size[1])];
        Ok(TensorType::new(x.dtype, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let scale = match self.scale {
            Some(s) if s[0] == s[1] => float(s[0]),
            Some(s) => format!("{}x{}", float(s[0]), float(s[1])),
            None => "none".into(),
        };
        let mode = match self.mode {
            UpsampleMode::Nearest => "nearest",
            UpsampleMode::Bilinear => "bilinear",
        };
        vec![
            ("size", format!("{}x{}", self.size[0], self.size[1])),
            ("scale", scale),
            ("mode", mode.into()),
            ("align_corners", self.align_corners.to_string()),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;

    #[test]
    fn upsample_takes_its_size() {
        let u = Upsample { size: [8, 6], scale: None, mode: UpsampleMode::Bilinear, align_corners: false };
        assert_eq!(run(&u, &[t(&[1, 3, 4, 3])]), Ok(t(&[1, 3, 8, 6])));
        let u = Upsample { size: [0, 6], ..u };
        assert!(run(&u, &[t(&[1, 3, 4, 3])]).is_err());
    }
}
