//! Normalisation: `batchnorm` (over axis 1), `layernorm` (over the last axis), `groupnorm`
//! (over groups of channels), and the per-channel affine a BatchNorm folds to, with the one
//! definition of that fold.

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, float};

/// Batch normalisation over axis 1 with affine parameters and running statistics.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BatchNorm {
    pub channels: i64,
    pub eps: f64,
    pub momentum: f64,
}

impl Operator for BatchNorm {
    fn kind_name(&self) -> &'static str {
        "batchnorm"
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = inputs[0];
        if x.rank() < 2 {
            return Err(ShapeError::new(format!("batchnorm expects at least 2 axes (N, C, ...), got {x}")));
        }
        if x.known_dim(1) != Some(self.channels) {
            return Err(ShapeError::new(format!("batchnorm over {} channels got {x}", self.channels)));
        }
        Ok(x.clone())
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("channels", self.channels.to_string()), ("eps", float(self.eps)), ("momentum", float(self.momentum))]
    }
}

/// `y = x * scale[c] + shift[c]` over axis 1: an inference-mode BatchNorm after folding.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ChannelAffine {
    pub channels: i64,
}

impl Operator for ChannelAffine {
    fn kind_name(&self) -> &'static str {
        "channel_affine"
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = inputs[0];
        if x.rank() < 2 || x.known_dim(1) != Some(self.channels) {
            return Err(ShapeError::new(format!("channel_affine over {} channels got {x}", self.channels)));
        }
        Ok(x.clone())
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("channels", self.channels.to_string())]
    }
}

/// Layer normalisation over the last axis.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LayerNorm {
    pub features: i64,
    pub eps: f64,
    pub affine: bool,
}

impl Operator for LayerNorm {
    fn kind_name(&self) -> &'static str {
        "layernorm"
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = inputs[0];
        if x.rank() < 1 || x.known_dim(x.rank() - 1) != Some(self.features) {
            return Err(ShapeError::new(format!("layernorm over {} features got {x}", self.features)));
        }
        if !(self.eps.is_finite() && self.eps >= 0.0) {
            return Err(ShapeError::new(format!("layernorm eps {} is not a finite non-negative number", self.eps)));
        }
        Ok(x.clone())
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("features", self.features.to_string()), ("eps", float(self.eps)), ("affine", self.affine.to_string())]
    }
}

/// Group normalisation (`nn.GroupNorm`): axis 1's `num_channels` channels in
/// `num_groups` groups of consecutive channels, each group of each sample normalised over
/// its channels and the remaining axes with the biased variance, then a per-channel affine
/// (`weight`, `bias`, `[num_channels]`) when `affine`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GroupNorm {
    pub num_groups: i64,
    pub num_channels: i64,
    pub eps: f64,
    pub affine: bool,
}

impl Operator for GroupNorm {
    fn kind_name(&self) -> &'static str {
        "groupnorm"
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let (x, g, c) = (inputs[0], self.num_groups, self.num_channels);
        if x.rank() < 2 || x.known_dim(1) != Some(c) {
            return Err(ShapeError::new(format!("groupnorm over {c} channels (axis 1) got {x}")));
        }
        if g < 1 || c % g != 0 {
            return Err(ShapeError::new(format!("groupnorm: {c} channels do not divide into {g} groups")));
        }
        if !(self.eps.is_finite() && self.eps >= 0.0) {
            return Err(ShapeError::new(format!("groupnorm eps {} is not a finite non-negative number", self.eps)));
        }
        Ok(x.clone())
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![
            ("num_groups", self.num_groups.to_string()),
            ("num_channels", self.num_channels.to_string()),
            ("eps", float(self.eps)),
            ("affine", self.affine.to_string()),
        ]
    }
}

/// One channel of an inference-mode BatchNorm as `y = scale * x + shift`, in f64:
/// `scale = gamma / sqrt(var + eps)`, `shift = beta - mean * scale`. Every place that
/// folds, moves or re-estimates a BatchNorm uses this one definition (through
/// [`batchnorm_affine`] for whole layers).
#[inline]
pub fn batchnorm_channel(gamma: f64, beta: f64, mean: f64, var: f64, eps: f64) -> (f64, f64) {
    let scale = gamma / (var + eps).sqrt();
    (scale, beta - mean * scale)
}

/// A BatchNorm layer's per-channel affine (see [`batchnorm_channel`]) from its parameters
/// and running statistics. A bias `prior` added before the BatchNorm (a conv's) folds into
/// the shift: `shift = beta + (prior - mean) * scale`.
pub fn batchnorm_affine(
    gamma: &[f32],
    beta: &[f32],
    mean: &[f32],
    var: &[f32],
    eps: f64,
    prior: Option<&[f32]>,
) -> (Vec<f64>, Vec<f64>) {
    (0..gamma.len())
        .map(|c| {
            let m = mean[c] as f64 - prior.map_or(0.0, |p| p[c] as f64);
            batchnorm_channel(gamma[c] as f64, beta[c] as f64, m, var[c] as f64, eps)
        })
        .unzip()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn batchnorm_affine_by_hand() {
        // gamma 2, var 3 + eps 1 -> scale 2 / 2 = 1; shift = 0.5 - 4 * 1 = -3.5.
        let (s, t) = batchnorm_affine(&[2.0, 1.0], &[0.5, 0.0], &[4.0, 1.0], &[3.0, 15.0], 1.0, None);
        assert_eq!(s, vec![1.0, 0.25]);
        assert_eq!(t, vec![-3.5, -0.25]);
        // A prior bias of 1 moves the shift by scale: -3.5 + 1 and -0.25 + 0.25.
        let (_, t) = batchnorm_affine(&[2.0, 1.0], &[0.5, 0.0], &[4.0, 1.0], &[3.0, 15.0], 1.0, Some(&[1.0, 1.0]));
        assert_eq!(t, vec![-2.5, 0.0]);
    }

    #[test]
    fn groupnorm_shape_rule() {
        use super::super::testutil::{run, t};
        let gn = |num_groups, num_channels| GroupNorm { num_groups, num_channels, eps: 1e-5, affine: true };
        assert_eq!(run(&gn(2, 6), &[t(&[3, 6, 5, 4])]), Ok(t(&[3, 6, 5, 4])));
        assert_eq!(run(&gn(6, 6), &[t(&[1, 6])]), Ok(t(&[1, 6])));
        let e = run(&gn(4, 6), &[t(&[3, 6, 5])]).expect_err("4 does not divide 6");
        assert_eq!(e.message, "groupnorm: 6 channels do not divide into 4 groups");
        let e = run(&gn(2, 8), &[t(&[3, 6, 5])]).expect_err("channels");
        assert_eq!(e.message, "groupnorm over 8 channels (axis 1) got f32[3, 6, 5]");
        assert!(run(&gn(0, 6), &[t(&[3, 6])]).is_err());
        assert!(run(&gn(1, 6), &[t(&[6])]).is_err());
    }
}
