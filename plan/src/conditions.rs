//! The conditions a plan serves: the spec's `variants` section as data.
//!
//! The axes and their levels, how each axis's level is found (a statistic of an input
//! against thresholds, or a metadata value snapped to the nearest level), the
//! missing-modality policies and the meld rule. The compiler's `check_variants` pass builds
//! a [`Conditions`] and the plan stores it; the runtime's selection reads it
//! (`readi_runtime::conditions`), and melding at compile time reads its lambdas.

use serde::{Deserialize, Serialize};

use crate::key::{KeyPart, VariantKey};

/// The checked `variants` section of a spec, as the runtime needs it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Conditions {
    pub axes: Vec<AxisSpec>,
    pub selectors: Vec<SelectorSpec>,
    /// `(modality, policy)` for modalities whose inputs are optional.
    pub missing: Vec<(String, MissingPolicy)>,
    pub meld: Option<MeldSpec>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AxisSpec {
    pub name: String,
    pub modality: String,
    pub levels: Vec<f64>,
    /// The level of the clear condition (the base model), if declared.
    pub clear: Option<f64>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum MissingPolicy {
    ZeroFill,
    Variant,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum KeySource {
    /// A run metadata value, snapped to the nearest level (or the clear level).
    Meta(String),
    /// A statistic of an input.
    Stat { stat: Statistic, input: String },
}

/// Statistics of an input tensor a selector may use.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Statistic {
    /// Mean value (images in [0, 1]: mean brightness).
    Brightness,
    /// Standard deviation.
    Contrast,
    /// Variance of the 4-neighbour Laplacian over the last two axes (low when blurred).
    LaplacianVar,
    /// Fraction of non-zero elements (lidar returns, occupied BEV cells).
    Density,
    /// Mean of the non-zero elements (the intensity of the returns there are).
    Intensity,
}

impl Statistic {
    /// Every statistic, in the order the language reference lists them.
    pub const ALL: [Statistic; 5] =
        [Statistic::Brightness, Statistic::Contrast, Statistic::LaplacianVar, Statistic::Density, Statistic::Intensity];

    pub fn from_name(name: &str) -> Option<Statistic> {
        Statistic::ALL.into_iter().find(|s| s.name() == name)
    }

    /// What it measures, for listings and messages.
    pub fn description(self) -> &'static str {
        match self {
            Statistic::Brightness => "mean value of an image",
            Statistic::Contrast => "standard deviation of an image",
            Statistic::LaplacianVar => "variance of the Laplacian of an image (low when blurred)",
            Statistic::Density => "fraction of non-zero cells or returns",
            Statistic::Intensity => "mean of the non-zero values (the intensity of the returns)",
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Statistic::Brightness => "brightness",
            Statistic::Contrast => "contrast",
            Statistic::LaplacianVar => "laplacian_var",
            Statistic::Density => "density",
            Statistic::Intensity => "intensity",
        }
    }
}

/// How one axis's level is found.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SelectorSpec {
    pub axis: String,
    pub source: KeySource,
    /// Threshold arms: the first whose bound the value is below decides; the last has no
    /// bound. Empty: the nearest level.
    pub arms: Vec<ArmSpec>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ArmSpec {
    /// `Some((t, inclusive))`: `< t` (`<= t` when inclusive); `None`: `else`.
    pub below: Option<(f64, bool)>,
    /// `None`: the clear condition.
    pub level: Option<f64>,
}

/// `meld camera = 0.8, lidar = 0.2`: how a combined condition interpolates two
/// mono-domain variants (the paper's `lambda_c * P_c + lambda_l * P_l`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MeldSpec {
    pub by: MeldBy,
    /// Lambda per modality or axis; they sum to 1.
    pub weights: Vec<(String, f64)>,
}

/// Whether a meld rule weighs modalities or axes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum MeldBy {
    Modality,
    Axis,
}

impl Conditions {
    /// Every variant key the spec declares: one per axis level, one per missing modality
    /// served by a variant (compiled into the plan or not).
    pub fn keys(&self) -> Vec<VariantKey> {
        let levels = self.axes.iter().flat_map(|a| a.levels.iter().map(|l| VariantKey::level(&a.name, *l)));
        let missing =
            self.missing.iter().filter(|(_, p)| *p == MissingPolicy::Variant).map(|(m, _)| VariantKey::missing(m));
        levels.chain(missing).collect()
    }

    /// The axis called `name`.
    pub fn axis(&self, name: &str) -> Option<&AxisSpec> {
        self.axes.iter().find(|a| a.name == name)
    }

    /// The lambdas of a melded key's parts, in the key's order, normalised to sum 1, or
    /// why the spec's meld rule does not combine them (each part must fall in its own meld
    /// group, a modality or an axis, that the rule weighs).
    pub fn meld_weights(&self, key: &VariantKey) -> Result<Vec<f64>, String> {
        let meld = self.meld.as_ref().ok_or("the spec has no `meld` rule")?;
        let mut groups: Vec<&str> = Vec::new();
        let mut lambdas = Vec::new();
        for p in key.parts() {
            let group = match p {
                KeyPart::Missing { modality } => modality.as_str(),
                KeyPart::Level { axis, .. } => {
                    let a = self.axis(axis).ok_or(format!("no axis `{axis}`"))?;
                    if meld.by == MeldBy::Axis { &a.name } else { &a.modality }
                }
            };
            if groups.contains(&group) {
                return Err(format!("two parts weigh on `{group}`"));
            }
            groups.push(group);
            let l = meld.weights.iter().find(|(n, _)| n == group).map(|(_, l)| *l);
            lambdas.push(l.ok_or(format!("the meld rule gives no lambda for `{group}`"))?);
        }
        let sum: f64 = lambdas.iter().sum();
        Ok(lambdas.iter().map(|l| l / sum).collect())
    }
}
