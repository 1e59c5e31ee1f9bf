//! Conditions in the field: choosing the variant from the inputs and run metadata.
//!
//! A plan compiled from a spec with a `variants` section carries its [`Conditions`]: the
//! axes and their levels, how each axis's level is found (a statistic of an input against
//! thresholds, or a metadata value snapped to the nearest level), the missing-modality
//! policies and the meld rule. [`select`] turns one frame's inputs and metadata into the
//! key of a variant the plan holds and the reasons for it ([`select_frame`] does the same
//! under any [`Conditions`], for any set of keys):
//!
//! 1. each absent optional input's modality follows its policy: `zero_fill` (the default)
//!    runs the zero-filled input and ignores the modality's selectors; `variant` selects
//!    `missing=<modality>`;
//! 2. every selector of a present modality computes its statistic (or reads its metadata)
//!    and picks a level; the clear level selects nothing;
//! 3. no condition selects the base; one selects its variant; several on different meld
//!    groups (modalities or axes, as the meld rule weighs them) select the melded variant
//!    `a=x+b=y` when the plan has it, and otherwise the component with the largest lambda
//!    (said so in the reasons); several without a meld rule covering them are an error.
//!
//! Statistics cost one pass over an input ([`statistic`]); a level a plan does not hold a
//! variant for falls back to the nearest compiled level of the same axis, or the base.

use std::borrow::Cow;

use rayon::prelude::*;
pub use readi_plan::conditions::*;
use readi_plan::key::VariantKey;
pub use readi_plan::key::fmt_level;

use crate::exec::Input;
use crate::plan::{Plan, escaped};

/// Sum and sum of squares in sixteen f32 lanes (so the loop vectorises), folded in f64
/// every block so long inputs keep their precision; blocks run in parallel.
fn sums(data: &[f32]) -> (f64, f64) {
    data.par_chunks(BLOCK).map(block_sums).reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1))
}

const BLOCK: usize = 1 << 14;

fn block_sums(block: &[f32]) -> (f64, f64) {
    let (mut s, mut q) = ([0.0f32; 16], [0.0f32; 16]);
    let mut lanes = block.chunks_exact(16);
    for c in &mut lanes {
        for ((s, q), &v) in s.iter_mut().zip(q.iter_mut()).zip(c) {
            *s += v;
            *q += v * v;
        }
    }
    for &v in lanes.remainder() {
        s[0] += v;
        q[0] += v * v;
    }
    (s.iter().map(|&v| v as f64).sum(), q.iter().map(|&v| v as f64).sum())
}

/// Number of non-zero elements and their sum.
fn nonzero(data: &[f32]) -> (usize, f64) {
    let block = |block: &[f32]| {
        let (mut c, mut s) = ([0u32; 16], [0.0f32; 16]);
        let mut lanes = block.chunks_exact(16);
        for l in &mut lanes {
            for ((c, s), &v) in c.iter_mut().zip(s.iter_mut()).zip(l) {
                *c += (v != 0.0) as u32;
                *s += v;
            }
        }
        for &v in lanes.remainder() {
            c[0] += (v != 0.0) as u32;
            s[0] += v;
        }
        (c.iter().map(|&v| v as usize).sum::<usize>(), s.iter().map(|&v| v as f64).sum::<f64>())
    };
    data.par_chunks(BLOCK).map(block).reduce(|| (0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1))
}

/// Sum and sum of squares of the 4-neighbour Laplacian over the interior of one plane.
fn laplacian_sums(plane: &[f32], h: usize, w: usize) -> (f64, f64) {
    let (mut sum, mut sq) = (0.0f64, 0.0f64);
    let mut lap = vec![0.0f32; w - 2];
    for y in 1..h - 1 {
        let row = &plane[y * w..(y + 1) * w];
        let up = &plane[(y - 1) * w + 1..y * w - 1];
        let down = &plane[(y + 1) * w + 1..(y + 2) * w - 1];
        let (left, mid, right) = (&row[..w - 2], &row[1..w - 1], &row[2..]);
        let neighbours = up.iter().zip(down).zip(left).zip(right);
        for ((l, &m), (((&u, &d), &a), &b)) in lap.iter_mut().zip(mid).zip(neighbours) {
            *l = u + d + a + b - 4.0 * m;
        }
        let (s, q) = block_sums(&lap);
        sum += s;
        sq += q;
    }
    (sum, sq)
}

/// The statistic of a tensor of `shape` (the last two axes are an image's rows and
/// columns): one vectorised pass, split over the global rayon pool.
pub fn statistic(stat: Statistic, data: &[f32], shape: &[usize]) -> f64 {
    if data.is_empty() {
        return 0.0;
    }
    let n = data.len() as f64;
    match stat {
        Statistic::Brightness => sums(data).0 / n,
        Statistic::Contrast => {
            let (sum, sq) = sums(data);
            let mean = sum / n;
            (sq / n - mean * mean).max(0.0).sqrt()
        }
        Statistic::Density => {
            let count = |b: &[f32]| b.iter().fold(0u32, |c, &v| c + (v != 0.0) as u32) as usize;
            data.par_chunks(BLOCK).map(count).sum::<usize>() as f64 / n
        }
        Statistic::Intensity => {
            let (count, sum) = nonzero(data);
            if count == 0 { 0.0 } else { sum / count as f64 }
        }
        Statistic::LaplacianVar => {
            let (h, w) = match shape {
                [.., h, w] if *h >= 3 && *w >= 3 => (*h, *w),
                _ => return 0.0,
            };
            let (sum, sq) = data
                .par_chunks_exact(h * w)
                .map(|p| laplacian_sums(p, h, w))
                .reduce(|| (0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
            let count = (data.len() / (h * w)) * (h - 2) * (w - 2);
            if count == 0 {
                return 0.0;
            }
            let mean = sum / count as f64;
            sq / count as f64 - mean * mean
        }
    }
}

/// One input of a frame, for selection: its data, or absent.
#[derive(Clone, Copy, Debug)]
pub struct FrameInput<'a> {
    pub name: &'a str,
    pub modality: Option<&'a str>,
    /// `None`: the input is absent (a missing sensor).
    pub data: Option<(&'a [f32], &'a [usize])>,
}

/// The outcome of selection: a key the plan holds, and why.
#[derive(Clone, Debug, PartialEq)]
pub struct Selection {
    pub key: VariantKey,
    pub reasons: Vec<String>,
}

/// Why no variant could be selected.
#[derive(Clone, Debug, PartialEq)]
pub enum SelectError {
    /// Conditions on several meld groups and no meld rule that covers them.
    NoMeld { conditions: Vec<String> },
    /// A required input is absent.
    MissingRequired { input: String },
    /// Metadata that no selector reads (a misspelt name would otherwise be ignored).
    UnknownMeta { name: String, known: Vec<String> },
}

impl std::fmt::Display for SelectError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SelectError::NoMeld { conditions } => write!(
                f,
                "conditions {} hold at once, and the spec has no meld rule combining them; \
                 add a `meld` rule to the variants section",
                conditions.join(" and ")
            ),
            SelectError::MissingRequired { input } => write!(f, "required input `{}` is absent", escaped(input)),
            SelectError::UnknownMeta { name, known } => {
                let known: Vec<String> = known.iter().map(|k| format!("`{}`", escaped(k))).collect();
                let read = if known.is_empty() { "none".to_string() } else { known.join(", ") };
                write!(f, "no selector reads metadata `{}` (the plan's selectors read: {read})", escaped(name))
            }
        }
    }
}

impl std::error::Error for SelectError {}

/// Chooses the variant for one frame under `conditions` (see the module doc). `has`
/// tells whether the plan holds a key.
pub fn select_frame(
    conditions: &Conditions,
    inputs: &[FrameInput<'_>],
    meta: &[(String, f64)],
    has: impl Fn(&VariantKey) -> bool,
) -> Result<Selection, SelectError> {
    let c = conditions;
    let mut reasons = Vec::new();
    // (the part's key, its axis if it is a level)
    let mut picked: Vec<(VariantKey, Option<&AxisSpec>)> = Vec::new();
    let mut absent_modalities: Vec<&str> = Vec::new();
    for i in inputs.iter().filter(|i| i.data.is_none()) {
        let m = i.modality.unwrap_or("");
        let policy = c.missing.iter().find(|(mm, _)| mm == m).map(|(_, p)| *p).unwrap_or(MissingPolicy::ZeroFill);
        if !absent_modalities.contains(&m) {
            absent_modalities.push(m);
            match policy {
                MissingPolicy::ZeroFill => {
                    reasons.push(format!("`{}` is absent: zero-filled ({} policy)", escaped(i.name), escaped(m)))
                }
                MissingPolicy::Variant => {
                    let key = VariantKey::missing(m);
                    reasons.push(format!("`{}` is absent: the {} policy selects `{key}`", escaped(i.name), escaped(m)));
                    picked.push((key, None));
                }
            }
        }
    }
    for s in &c.selectors {
        let Some(axis) = c.axis(&s.axis) else { continue };
        if absent_modalities.contains(&axis.modality.as_str()) {
            continue;
        }
        let (value, source) = match &s.source {
            KeySource::Meta(k) => match meta.iter().find(|(n, _)| n == k) {
                Some((_, v)) => (*v, format!("meta `{}` = {}", escaped(k), fmt_value(*v))),
                None => {
                    reasons.push(format!("{}: no metadata `{}`; clear", escaped(&s.axis), escaped(k)));
                    continue;
                }
            },
            KeySource::Stat { stat, input } => match inputs.iter().find(|i| i.name == input).and_then(|i| i.data) {
                Some((data, shape)) => {
                    let v = statistic(*stat, data, shape);
                    (v, format!("{}({}) = {}", stat.name(), escaped(input), fmt_value(v)))
                }
                None => continue,
            },
        };
        let level = if s.arms.is_empty() {
            nearest(axis, value)
        } else {
            s.arms
                .iter()
                .find(|a| match a.below {
                    Some((t, inclusive)) => value < t || (inclusive && value == t),
                    None => true,
                })
                .and_then(|a| a.level)
        };
        match level {
            None => reasons.push(format!("{}: {source} -> clear", escaped(&s.axis))),
            Some(l) => {
                let key = VariantKey::level(&s.axis, l);
                reasons.push(format!("{}: {source} -> {key}", escaped(&s.axis)));
                picked.push((key, Some(axis)));
            }
        }
    }
    // Keys the plan holds: the nearest compiled level of the axis, else nothing.
    let mut keys: Vec<VariantKey> = Vec::new();
    for (key, axis) in picked {
        if has(&key) {
            keys.push(key);
            continue;
        }
        let alt = axis.and_then(|a| {
            let want = match key.parts() {
                [readi_plan::key::KeyPart::Level { level, .. }] => *level,
                _ => return None,
            };
            let mut levels: Vec<f64> =
                a.levels.iter().copied().filter(|l| has(&VariantKey::level(&a.name, *l))).collect();
            levels.sort_by(|x, y| (x - want).abs().total_cmp(&(y - want).abs()));
            levels.first().map(|l| VariantKey::level(&a.name, *l))
        });
        match alt {
            Some(k) => {
                reasons.push(format!("the plan has no `{key}`; using the nearest compiled `{k}`"));
                keys.push(k);
            }
            None => reasons.push(format!("the plan has no `{key}` variant; ignored")),
        }
    }
    match keys.len() {
        0 => Ok(Selection { key: VariantKey::base(), reasons }),
        1 => Ok(Selection { key: keys.remove(0), reasons }),
        _ => {
            let shown = || keys.iter().map(|k| k.to_string()).collect::<Vec<_>>();
            let no_meld = || SelectError::NoMeld { conditions: shown() };
            let melded = VariantKey::meld(&keys).map_err(|_| no_meld())?;
            let Ok(lambdas) = c.meld_weights(&melded) else {
                return Err(no_meld());
            };
            if has(&melded) {
                reasons.push(format!("meld rule combines {}", shown().join(" and ")));
                return Ok(Selection { key: melded, reasons });
            }
            // The lambdas follow the melded key's parts.
            let best = lambdas.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map(|(i, _)| i).unwrap_or(0);
            let Some(part) = melded.part_keys().nth(best) else { return Err(no_meld()) };
            reasons
                .push(format!("the plan has no melded `{melded}`; using `{part}` (largest lambda, {})", lambdas[best]));
            Ok(Selection { key: part, reasons })
        }
    }
}

fn nearest(axis: &AxisSpec, value: f64) -> Option<f64> {
    let mut best: Option<(f64, Option<f64>)> = axis.clear.map(|c| ((value - c).abs(), None));
    for &l in &axis.levels {
        let d = (value - l).abs();
        if best.is_none_or(|(bd, _)| d < bd) {
            best = Some((d, Some(l)));
        }
    }
    best.and_then(|(_, l)| l)
}

fn fmt_value(v: f64) -> String {
    if v != 0.0 && (v.abs() < 1e-3 || v.abs() >= 1e5) { format!("{v:.3e}") } else { format!("{v:.4}") }
}

/// Chooses `plan`'s variant for one frame: `inputs` as given to
/// [`Session::run`](crate::exec::Session::run) (absent optional inputs left out) and run
/// metadata such as a weather service's `fog_density`. A plan without conditions runs the
/// base. For a multi-view input (`[N, views, C, H, W]`), statistics are computed over the
/// views that are not all zero, so a dropped camera does not read as darkness.
pub fn select(plan: &Plan, inputs: &[Input<'_>], meta: &[(String, f64)]) -> Result<Selection, SelectError> {
    let m = &plan.manifest;
    for spec in &m.inputs {
        if !spec.optional && !inputs.iter().any(|i| i.name == spec.name) {
            return Err(SelectError::MissingRequired { input: spec.name.clone() });
        }
    }
    let read_meta: Vec<&str> = m
        .conditions
        .iter()
        .flat_map(|c| &c.selectors)
        .filter_map(|s| match &s.source {
            KeySource::Meta(k) => Some(k.as_str()),
            KeySource::Stat { .. } => None,
        })
        .collect();
    if let Some((name, _)) = meta.iter().find(|(n, _)| !read_meta.contains(&n.as_str())) {
        return Err(SelectError::UnknownMeta {
            name: name.clone(),
            known: read_meta.iter().map(|k| k.to_string()).collect(),
        });
    }
    let Some(c) = &m.conditions else {
        return Ok(Selection { key: VariantKey::base(), reasons: vec!["the plan declares no conditions".into()] });
    };
    // Each input as selection reads it: a multi-view input only with the views present,
    // as `[views, C, H, W]`.
    let given: Vec<Option<ViewedInput<'_>>> = m
        .inputs
        .iter()
        .map(|spec| {
            let i = inputs.iter().find(|i| i.name == spec.name)?;
            if i.shape.len() < 5 {
                return Some((Cow::Borrowed(i.data), i.shape.to_vec()));
            }
            let views = present_views(i.data, i.shape);
            let per_view: usize = i.shape[2..].iter().product();
            let mut shape = vec![views.len() / per_view.max(1)];
            shape.extend_from_slice(&i.shape[2..]);
            Some((views, shape))
        })
        .collect();
    let frame: Vec<FrameInput<'_>> = m
        .inputs
        .iter()
        .zip(&given)
        .map(|(spec, g)| FrameInput {
            name: &spec.name,
            modality: spec.modality.as_deref(),
            data: g.as_ref().map(|(d, shape)| (d.as_ref(), shape.as_slice())),
        })
        .collect();
    select_frame(c, &frame, meta, |k| plan.variant_index_of(k).is_some())
}

/// The missing-modality variant the spec's policy asks for when an optional input is
/// absent (`missing lidar: variant` and no `lidar_bev` given), if `plan` holds it, with
/// the reason. Selectors are not consulted: this is what a run without automatic
/// selection still owes the spec.
pub fn missing_variant(plan: &Plan, inputs: &[Input<'_>]) -> Option<(VariantKey, String)> {
    let c = plan.manifest.conditions.as_ref()?;
    plan.manifest.inputs.iter().filter(|i| !inputs.iter().any(|g| g.name == i.name)).find_map(|i| {
        let m = i.modality.as_deref()?;
        let policy = c.missing.iter().find(|(mm, _)| mm == m).map(|(_, p)| *p)?;
        let key = VariantKey::missing(m);
        (policy == MissingPolicy::Variant && plan.variant_index_of(&key).is_some()).then(|| {
            let why = format!("`{}` is absent: the {} policy selects `{key}`", escaped(&i.name), escaped(m));
            (key, why)
        })
    })
}

/// An input's data and shape as selection reads it.
type ViewedInput<'a> = (Cow<'a, [f32]>, Vec<usize>);

/// The views (axis 1) of a multi-view tensor that are not all zero, concatenated (batch 0
/// first); the data itself when no view is dropped (or every view is).
fn present_views<'a>(data: &'a [f32], shape: &[usize]) -> Cow<'a, [f32]> {
    let per_view: usize = shape[2..].iter().product();
    if per_view == 0 {
        return Cow::Borrowed(data);
    }
    let present: Vec<&[f32]> = data.chunks_exact(per_view).filter(|v| v.iter().any(|x| *x != 0.0)).collect();
    if present.is_empty() || present.len() * per_view == data.len() {
        Cow::Borrowed(data)
    } else {
        Cow::Owned(present.concat())
    }
}

/// Zeroes views `drop` (axis 1) of a multi-view input `[N, views, ...]`: a dropped camera.
pub fn drop_views(data: &mut [f32], shape: &[usize], drop: &[usize]) -> Result<(), String> {
    if shape.len() < 5 {
        return Err(format!("an input of shape {shape:?} is not multi-view (expected [N, views, C, H, W])"));
    }
    let views = shape[1];
    if let Some(v) = drop.iter().find(|v| **v >= views) {
        return Err(format!("view {v} does not exist (the input has {views} views, 0..{})", views.saturating_sub(1)));
    }
    let per_view: usize = shape[2..].iter().product();
    for (i, chunk) in data.chunks_exact_mut(per_view.max(1)).enumerate() {
        if drop.contains(&(i % views)) {
            chunk.fill(0.0);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> Conditions {
        Conditions {
            axes: vec![
                AxisSpec {
                    name: "fog".into(),
                    modality: "lidar".into(),
                    levels: vec![0.03, 0.06, 0.1],
                    clear: Some(0.0),
                },
                AxisSpec { name: "gamma".into(), modality: "camera".into(), levels: vec![0.5, 2.0], clear: Some(1.0) },
            ],
            selectors: vec![
                SelectorSpec { axis: "fog".into(), source: KeySource::Meta("fog_density".into()), arms: vec![] },
                SelectorSpec {
                    axis: "gamma".into(),
                    source: KeySource::Stat { stat: Statistic::Brightness, input: "cam".into() },
                    arms: vec![
                        ArmSpec { below: Some((0.3, false)), level: Some(0.5) },
                        ArmSpec { below: Some((0.7, false)), level: None },
                        ArmSpec { below: None, level: Some(2.0) },
                    ],
                },
            ],
            missing: vec![("lidar".into(), MissingPolicy::Variant)],
            meld: Some(MeldSpec { by: MeldBy::Modality, weights: vec![("camera".into(), 0.8), ("lidar".into(), 0.2)] }),
        }
    }

    #[test]
    fn statistics_match_hand_computed_values() {
        let x = [0.0f32, 1.0, 0.0, 3.0];
        assert_eq!(statistic(Statistic::Brightness, &x, &[4]), 1.0);
        assert_eq!(statistic(Statistic::Contrast, &x, &[4]), ((1.0f64 + 0.0 + 1.0 + 4.0) / 4.0).sqrt());
        assert_eq!(statistic(Statistic::Density, &x, &[4]), 0.5);
        assert_eq!(statistic(Statistic::Intensity, &x, &[4]), 2.0);
        // A 3x3 plane has one interior pixel: Laplacian 1+1+1+1-4*5 = -16, variance 0.
        let p = [1.0f32, 1.0, 1.0, 1.0, 5.0, 1.0, 1.0, 1.0, 1.0];
        assert_eq!(statistic(Statistic::LaplacianVar, &p, &[3, 3]), 0.0);
        // A 3x4 plane: two interior pixels with Laplacians -1 - 16 = -17 and 4 + 4 = 8:
        // mean -4.5, variance 12.5^2 = 156.25.
        let q = [0.0f32, 0.0, 0.0, 0.0, 0.0, 4.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert_eq!(statistic(Statistic::LaplacianVar, &q, &[3, 4]), 156.25);
    }

    #[test]
    fn thresholds_meta_and_meld_choose_the_key() {
        let s = spec();
        let dark = vec![0.1f32; 16];
        let bright = vec![0.5f32; 16];
        let lidar = vec![1.0f32; 4];
        let frame = |cam: &'static [f32], lid: Option<&'static [f32]>| {
            vec![
                FrameInput { name: "cam", modality: Some("camera"), data: Some((cam, &[4, 4])) },
                FrameInput { name: "lid", modality: Some("lidar"), data: lid.map(|d| (d, &[4usize][..])) },
            ]
        };
        let leak = |v: Vec<f32>| -> &'static [f32] { Box::leak(v.into_boxed_slice()) };
        let (dark, bright, lidar) = (leak(dark), leak(bright), leak(lidar));
        let all = |_: &VariantKey| true;
        let sel = select_frame(&s, &frame(bright, Some(lidar)), &[], all).expect("selects");
        assert_eq!(sel.key.to_string(), "base");
        let sel = select_frame(&s, &frame(dark, Some(lidar)), &[], all).expect("selects");
        assert_eq!(sel.key.to_string(), "gamma=0.5");
        assert!(sel.reasons.iter().any(|r| r.contains("brightness(cam) = 0.1000 -> gamma=0.5")), "{:?}", sel.reasons);
        // Metadata snaps to the nearest level; 0.01 is nearer the clear 0.
        let meta = |v: f64| vec![("fog_density".to_string(), v)];
        assert_eq!(
            select_frame(&s, &frame(bright, Some(lidar)), &meta(0.07), all).expect("s").key.to_string(),
            "fog=0.06"
        );
        assert_eq!(select_frame(&s, &frame(bright, Some(lidar)), &meta(0.01), all).expect("s").key.to_string(), "base");
        // Two modalities: the melded key when the plan has it, else the larger lambda.
        assert_eq!(
            select_frame(&s, &frame(dark, Some(lidar)), &meta(0.1), all).expect("s").key.to_string(),
            "fog=0.1+gamma=0.5"
        );
        let no_meld = |k: &VariantKey| !k.is_meld();
        let sel = select_frame(&s, &frame(dark, Some(lidar)), &meta(0.1), no_meld).expect("s");
        assert_eq!(sel.key.to_string(), "gamma=0.5");
        assert!(sel.reasons.iter().any(|r| r.contains("no melded")));
        // Without a meld rule: an error naming both.
        let mut plain = s.clone();
        plain.meld = None;
        let e = select_frame(&plain, &frame(dark, Some(lidar)), &meta(0.1), all).expect_err("no meld");
        assert!(e.to_string().contains("gamma=0.5") && e.to_string().contains("fog=0.1"), "{e}");
        // A missing lidar: its policy's variant; the fog selector is skipped.
        let sel = select_frame(&s, &frame(bright, None), &meta(0.1), all).expect("s");
        assert_eq!(sel.key.to_string(), "missing=lidar");
        // A level the plan lacks: the nearest compiled one.
        let only = |k: &VariantKey| k.to_string() == "fog=0.03";
        let sel = select_frame(&s, &frame(bright, Some(lidar)), &meta(0.1), only).expect("s");
        assert_eq!(sel.key.to_string(), "fog=0.03");
    }
}
