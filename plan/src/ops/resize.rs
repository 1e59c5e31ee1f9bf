//! `upsample`: resize of the last two axes of NCHW to a fixed size; `pixel_shuffle` and
//! `pixel_unshuffle`: channels moved into space and back.

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

/// `pixel_shuffle` (`[N, C·r², H, W]` to `[N, C, H·r, W·r]`, `out[n, c, h·r + i, w·r + j]
/// = x[n, c·r² + i·r + j, h, w]`) with `r = factor`, or its inverse `pixel_unshuffle`
/// (`[N, C, H·r, W·r]` to `[N, C·r², H, W]`), as PyTorch's.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct PixelShuffle {
    pub factor: i64,
    /// `pixel_unshuffle`.
    pub inverse: bool,
}

impl Operator for PixelShuffle {
    fn kind_name(&self) -> &'static str {
        if self.inverse { "pixel_unshuffle" } else { "pixel_shuffle" }
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let name = self.kind_name();
        let x = nchw(inputs[0], name)?;
        let r = self.factor;
        let rr = r.checked_mul(r).filter(|_| r >= 1).ok_or_else(|| ShapeError::new(format!("{name} factor {r}")))?;
        let c =
            x.known_dim(1).ok_or_else(|| ShapeError::new(format!("{name} needs a known channel count, got {x}")))?;
        let rd = Dim::known(r);
        let overflow = || ShapeError::new(format!("{name} by {r} of {x}: a size overflows"));
        let shape = if self.inverse {
            let mut hw = Vec::new();
            for a in 2..4 {
                let d = x.shape[a].checked_div(&rd).ok_or_else(|| {
                    ShapeError::new(format!("{name} by {r} needs spatial sizes divisible by {r}, got {x}"))
                })?;
                hw.push(d);
            }
            let c = Dim::known(c.checked_mul(rr).ok_or_else(overflow)?);
            vec![x.shape[0].clone(), c, hw[0].clone(), hw[1].clone()]
        } else {
            if c % rr != 0 {
                return Err(ShapeError::new(format!("{name} by {r} needs channels divisible by {rr}, got {x}")));
            }
            let h = x.shape[2].checked_mul(&rd).ok_or_else(overflow)?;
            let w = x.shape[3].checked_mul(&rd).ok_or_else(overflow)?;
            vec![x.shape[0].clone(), Dim::known(c / rr), h, w]
        };
        Ok(TensorType::new(x.dtype, shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![(if self.inverse { "downscale_factor" } else { "upscale_factor" }, self.factor.to_string())]
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

    #[test]
    fn pixel_shuffle_shapes() {
        use super::super::testutil::{run, t};
        let ps = |factor, inverse| PixelShuffle { factor, inverse };
        assert_eq!(run(&ps(2, false), &[t(&[1, 12, 3, 5])]), Ok(t(&[1, 3, 6, 10])));
        assert_eq!(run(&ps(3, true), &[t(&[2, 2, 6, 9])]), Ok(t(&[2, 18, 2, 3])));
        let e = run(&ps(2, false), &[t(&[1, 6, 3, 5])]).expect_err("6 % 4");
        assert_eq!(e.message, "pixel_shuffle by 2 needs channels divisible by 4, got f32[1, 6, 3, 5]");
        let e = run(&ps(2, true), &[t(&[1, 6, 3, 4])]).expect_err("3 % 2");
        assert_eq!(e.message, "pixel_unshuffle by 2 needs spatial sizes divisible by 2, got f32[1, 6, 3, 4]");
        assert!(run(&ps(0, false), &[t(&[1, 6, 3, 4])]).is_err());
    }
}
