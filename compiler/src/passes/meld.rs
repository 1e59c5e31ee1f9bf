//! `meld`: builds the melded variants `--meld` asks for (`fog=0.06+gamma=0.5`) from the
//! bound variants that are their parts, by the paper's rule (t-READi, "Putting Everything
//! Together"): layers only one part tuned are taken whole, only overlapping layers are
//! interpolated.
//!
//! The unit is the *layer*: the node an owned tensor belongs to (`<layer>.<slot>`), where
//! a LoRA's `<layer>.lora_A.weight` and `<layer>.lora_B.weight` belong to the adapted
//! layer `<layer>`, and an adapter's `<L>.adapter.{down,up}.*` to the adapter module
//! `<L>.adapter`. A part *owns* a layer when its files provide any tensor of it
//! ([`VariantInfo::provided`]). Per layer, with owners `O` among the parts:
//!
//! * no owner: the base values;
//! * one owner: that owner's value of every tensor of the layer, bit for bit (the paper's
//!   "straightforward update" of the exclusive layers);
//! * two or more: every tensor of the layer is `sum_{i in O} l'_i P_i(t)` with
//!   `l'_i = l_i / sum_{j in O} l_j`, the spec's lambdas renormalised over the owners so
//!   that they sum to 1 as the paper requires (with two parts that both own the layer this
//!   is exactly `lambda_c P_c + lambda_l P_l`). `P_i(t)` is the part's value, the base's
//!   for a tensor of the layer it did not provide. Accumulated in f64.
//!
//! A LoRA layer with two or more owners is melded on the updates, not on `A` and `B`
//! (whose interpolation would give `(sum l B)(sum l A)`, with cross terms): each owner's
//! effective weight is `W_i + scale * B_i A_i` (PEFT's merge; for a conv `A` is
//! `[rank, in * kh * kw]`, `B` is `[out, rank]`; `W_i` is the base weight unless a rule
//! tunes it), and the melded variant is served that interpolation as a merged weight:
//! its `<layer>.weight` becomes `sum l'_i (W_i + scale B_i A_i)` and its `lora_A`/`lora_B`
//! stay the base's zeros. An owner that gave no LoRA contributes `dW = 0`. This holds with
//! `--lora merge` and `--lora branch` alike (the later passes derive what varies); in
//! branch mode the melded variant therefore stores the layer's whole weight. (Not
//! implemented: serving it as a rank-sum branch `[l'_1 B_1 ... l'_n B_n] [A_1; ...; A_n]`,
//! which needs a LoRA of another rank in the melded variant.) A LoRA layer with one owner
//! keeps the owner's `A` and `B`.
//!
//! Errors: a key that is not a combination of declared keys, a part that was not given, a
//! meld the rule does not cover, a meld given twice, an overlapping layer whose owners all
//! have lambda 0, a melded value that overflows f32.
//!
//! Produces: the table with one more variant per meld, whose origin says how many layers
//! were taken whole and how many interpolated. Does nothing without `--meld`. Changes
//! nothing in the graph. Assumes `bind_variants` ran.

use std::collections::BTreeMap;

use readi_grammar::diag::{Code, Diagnostic, Diagnostics};
use readi_plan::VariantKey;

use super::bind_variants::{not_bound, same_bits};
use super::{BackendInputs, Output};
use crate::adapt::Injection;
use crate::ir::NodeId;
use crate::module::Module;
use crate::weights::tensors::{Data, TensorTable, VariantInfo, first_non_finite};
use crate::weights::variants::canonical_key;

pub fn run(module: &Module, inputs: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let mut table = module.tensors.clone().ok_or_else(not_bound)?;
    let err = |m: String| Diagnostics(vec![Diagnostic::error(Code::VariantWeights, m)]);
    let declared = module.variants.as_ref().map(|v| v.keys()).unwrap_or_default();
    let layers = if inputs.opts.melds.is_empty() { Vec::new() } else { layers(module, &table) };
    for key in &inputs.opts.melds {
        let melded = canonical_key(key, &declared).filter(VariantKey::is_meld).ok_or_else(|| {
            err(format!("`{key}` is not a combination of declared keys (write `fog=0.06+gamma=0.5`)"))
        })?;
        if table.variants.iter().any(|v| v.key == melded) {
            return Err(err(format!("variant `{melded}` is given twice")));
        }
        let spec = module.variants.as_ref().ok_or_else(|| err("the spec has no variants section".into()))?;
        let lambdas = spec.meld_weights(&melded).map_err(|m| err(format!("cannot meld `{melded}`: {m}")))?;
        let mut parts = Vec::new();
        for part in melded.part_keys() {
            let at = table.variants.iter().position(|v| v.key == part);
            parts.push(1 + at.ok_or_else(|| err(format!("cannot meld `{melded}`: no variant `{part}` is given")))?);
        }
        let m = meld(&table, &layers, &parts, &lambdas).map_err(|m| err(format!("cannot meld `{melded}`: {m}")))?;
        let shown: Vec<String> = melded.part_keys().map(|k| k.to_string()).collect();
        for (name, data) in &m.values {
            let Some(data) = data else { continue };
            if let Some((i, x)) = first_non_finite(data) {
                let terms: Vec<String> = shown.iter().zip(&lambdas).map(|(k, l)| format!("{l} * `{k}`")).collect();
                return Err(err(format!(
                    "melded tensor `{name}` of `{melded}` is {x} at flat index {i}: the sum {} overflows f32",
                    terms.join(" + ")
                )));
            }
        }
        let n = |k: usize| if k == 1 { "1 layer".to_string() } else { format!("{k} layers") };
        let origin = format!(
            "meld of {} ({} taken whole from one part, {} interpolated)",
            shown.join(" and "),
            n(m.exclusive),
            n(m.overlapping)
        );
        let provided = parts.iter().flat_map(|&v| table.variants[v - 1].provided.iter().cloned()).collect();
        table.variants.push(VariantInfo { key: melded, fallback: Vec::new(), provided, origin });
        let v = table.variant_count();
        let values: BTreeMap<String, Option<Data>> = m.values.into_iter().collect();
        for (name, t) in table.iter_mut() {
            t.variants.resize(v, None);
            if let Some(Some(data)) = values.get(name)
                && !same_bits(data, &t.base)
            {
                t.variants[v - 1] = Some(data.clone());
            }
        }
    }
    Ok(Output::Tensors(Box::new(table)))
}

/// A layer of the meld: the owned tensors that belong to one node (or one adapter).
#[derive(Clone, Debug, PartialEq)]
pub struct Layer {
    /// For messages: the node's path, `<L>.adapter` for an adapter.
    pub name: String,
    /// Its owned tensors (a LoRA layer's include `lora_A` and `lora_B`).
    pub tensors: Vec<String>,
    /// The LoRA on the layer, if any.
    pub lora: Option<Lora>,
}

/// A LoRA branch: `weight + scale * b a`, `a` of shape `[rank, cols]`, `b` `[rows, rank]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Lora {
    /// The adapted layer's own weight (not owned unless a rule tunes it).
    pub weight: String,
    pub a: String,
    pub b: String,
    pub rank: usize,
    pub scale: f64,
}

/// The owned tensors grouped by layer (see the module documentation), in name order.
pub fn layers(module: &Module, table: &TensorTable) -> Vec<Layer> {
    let g = &module.graph;
    // Injected nodes belong to the layer they adapt.
    let mut anchor: BTreeMap<NodeId, NodeId> = BTreeMap::new();
    let mut loras: BTreeMap<NodeId, Lora> = BTreeMap::new();
    let mut names: BTreeMap<NodeId, String> = BTreeMap::new();
    for inj in module.adapt.iter().flat_map(|p| &p.injections) {
        match *inj {
            Injection::Lora { base, a, b, factor, .. } => {
                anchor.insert(a, base);
                anchor.insert(b, base);
                let name = |n: NodeId| crate::ir::join_path(&g.node(n).path, "weight");
                let rank = g.node(a).params.first().and_then(|s| s.shape.first()).copied().unwrap_or(1).max(1);
                let weight =
                    g.node(base).params.iter().find(|s| s.name == "weight").map(|s| g.node(base).param_name(s));
                loras.insert(
                    base,
                    Lora {
                        weight: weight.unwrap_or_else(|| name(base)),
                        a: name(a),
                        b: name(b),
                        rank: rank as usize,
                        scale: factor,
                    },
                );
            }
            Injection::Adapter { down, up, .. } => {
                anchor.insert(up, down);
                let path = &g.node(down).path;
                names.insert(down, path.strip_suffix(".down").unwrap_or(path).to_string());
            }
        }
    }
    let mut by_node: BTreeMap<NodeId, Layer> = BTreeMap::new();
    for (name, o) in &table.owned {
        let node = anchor.get(&o.node).copied().unwrap_or(o.node);
        let layer = by_node.entry(node).or_insert_with(|| Layer {
            name: names.get(&node).cloned().unwrap_or_else(|| g.node(node).path.clone()),
            tensors: Vec::new(),
            lora: loras.get(&node).cloned(),
        });
        layer.tensors.push(name.clone());
    }
    let mut out: Vec<Layer> = by_node.into_values().collect();
    out.sort_by(|a, b| a.name.cmp(&b.name));
    out
}

/// A meld's values: per tensor of an owned layer, the melded variant's value (`None`: the
/// base's), and how many layers were taken whole and how many interpolated.
#[derive(Debug, Default)]
pub struct Melded {
    pub values: Vec<(String, Option<Data>)>,
    pub exclusive: usize,
    pub overlapping: usize,
}

/// The meld of the variants `parts` (table indices, 1 is the first variant) with weights
/// `lambdas` over `layers`, by the rule of the module documentation.
pub fn meld(table: &TensorTable, layers: &[Layer], parts: &[usize], lambdas: &[f64]) -> Result<Melded, String> {
    let mut out = Melded::default();
    let value = |name: &str, v: usize| table.get(name).map(|t| t.value(v));
    for layer in layers {
        let owners: Vec<(usize, f64)> = parts
            .iter()
            .zip(lambdas)
            .filter(|(v, _)| layer.tensors.iter().any(|n| table.variants[**v - 1].provided.contains(n)))
            .map(|(v, l)| (*v, *l))
            .collect();
        match owners.as_slice() {
            [] => {}
            [(v, _)] => {
                out.exclusive += 1;
                for name in &layer.tensors {
                    let Some(t) = table.get(name) else { continue };
                    out.values.push((name.clone(), t.variants[v - 1].clone()));
                }
            }
            _ => {
                out.overlapping += 1;
                let sum: f64 = owners.iter().map(|(_, l)| l).sum();
                if sum <= 0.0 || !sum.is_finite() {
                    return Err(format!("every part that tunes layer `{}` has lambda 0", layer.name));
                }
                let owners: Vec<(usize, f64)> = owners.iter().map(|&(v, l)| (v, l / sum)).collect();
                let lora = layer.lora.as_ref();
                for name in &layer.tensors {
                    let Some(t) = table.get(name) else { continue };
                    if let Some(lora) = lora
                        && (*name == lora.a || *name == lora.b || *name == lora.weight)
                    {
                        continue;
                    }
                    let mut acc = vec![0.0f64; t.numel()];
                    for &(v, l) in &owners {
                        for (a, x) in acc.iter_mut().zip(t.value(v)) {
                            *a += l * *x as f64;
                        }
                    }
                    out.values.push((name.clone(), Some(to_data(acc))));
                }
                if let Some(lora) = lora {
                    let (Some(w), Some(_), Some(_)) = (table.get(&lora.weight), table.get(&lora.a), table.get(&lora.b))
                    else {
                        return Err(format!("the LoRA of layer `{}` is not bound", layer.name));
                    };
                    let mut acc = vec![0.0f64; w.numel()];
                    for &(v, l) in &owners {
                        let (Some(wv), Some(a), Some(b)) =
                            (value(&lora.weight, v), value(&lora.a, v), value(&lora.b, v))
                        else {
                            continue;
                        };
                        add_effective(&mut acc, l, wv, a, b, lora.rank, lora.scale)?;
                    }
                    out.values.push((lora.weight.clone(), Some(to_data(acc))));
                    // The update is served in the weight: the melded variant's A and B are the base's.
                    out.values.push((lora.a.clone(), None));
                    out.values.push((lora.b.clone(), None));
                }
            }
        }
    }
    Ok(out)
}

fn to_data(acc: Vec<f64>) -> Data {
    acc.into_iter().map(|v| v as f32).collect::<Vec<f32>>().into()
}

/// `acc += l * (w + scale * b a)`, with `a` `[rank, cols]` and `b` `[rows, rank]`
/// flattened, `w` `[rows, cols]`.
fn add_effective(
    acc: &mut [f64],
    l: f64,
    w: &[f32],
    a: &[f32],
    b: &[f32],
    rank: usize,
    scale: f64,
) -> Result<(), String> {
    let cols = a.len() / rank;
    let rows = b.len() / rank;
    if rows * cols != w.len() || rows * rank != b.len() || rank * cols != a.len() {
        return Err(format!(
            "LoRA shapes do not match: weight {} values, A {} and B {} at rank {rank}",
            w.len(),
            a.len(),
            b.len()
        ));
    }
    // A part that gave no LoRA contributes its weight alone.
    if b.iter().all(|x| *x == 0.0) || a.iter().all(|x| *x == 0.0) {
        for (acc, &w) in acc.iter_mut().zip(w) {
            *acc += l * w as f64;
        }
        return Ok(());
    }
    for ((acc, &w), d) in acc.iter_mut().zip(w).zip(super::merge_lora::lora_delta(a, b, rank)) {
        *acc += l * (w as f64 + scale * d);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::weights::tensors::Tensor;

    /// A table of `tensors` (name, base, one value per variant: `None` where it reads
    /// the base) and variants that each provide the named tensors.
    /// A tensor of a test table: name, base value, per variant its value or `None`.
    type Row<'a> = (&'a str, Vec<f32>, Vec<Option<Vec<f32>>>);

    fn table(tensors: &[Row<'_>], provided: &[&[&str]]) -> TensorTable {
        let mut t = TensorTable::default();
        for (name, base, values) in tensors {
            let mut x = Tensor::param(name, vec![base.len()], Data::from(base.as_slice()), provided.len());
            for (i, v) in values.iter().enumerate() {
                x.variants[i] = v.as_ref().map(|v| Data::from(v.as_slice()));
            }
            t.insert(name.to_string(), x);
        }
        for (i, p) in provided.iter().enumerate() {
            t.variants.push(VariantInfo {
                key: VariantKey::parse(&format!("a{i}=1")).expect("key"),
                fallback: Vec::new(),
                provided: p.iter().map(|s| s.to_string()).collect(),
                origin: String::new(),
            });
        }
        t
    }

    fn layer(name: &str, tensors: &[&str]) -> Layer {
        Layer { name: name.into(), tensors: tensors.iter().map(|s| s.to_string()).collect(), lora: None }
    }

    fn get<'a>(m: &'a Melded, name: &str) -> Option<&'a [f32]> {
        m.values.iter().find(|(n, _)| n == name).and_then(|(_, d)| d.as_deref())
    }

    #[test]
    fn an_exclusive_layer_is_taken_whole_and_an_overlapping_one_interpolated() {
        // Layer `x` only part 1 tunes; layer `y` both tune (part 2 gave only y.bias).
        let t = table(
            &[
                ("x.w", vec![1.0, 1.0], vec![Some(vec![0.1f32, 0.7]), None]),
                ("y.w", vec![2.0], vec![Some(vec![4.0]), None]),
                ("y.b", vec![0.0], vec![Some(vec![1.0]), Some(vec![3.0])]),
            ],
            &[&["x.w", "y.w", "y.b"], &["y.b"]],
        );
        let layers = [layer("x", &["x.w"]), layer("y", &["y.b", "y.w"])];
        let m = meld(&t, &layers, &[1, 2], &[0.25, 0.75]).expect("melds");
        assert_eq!((m.exclusive, m.overlapping), (1, 1));
        // Whole, bit for bit: not 0.25 * 0.1 + 0.75 * 1.0.
        assert_eq!(
            get(&m, "x.w").expect("x.w").iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            [0.1f32.to_bits(), 0.7f32.to_bits()]
        );
        // y.w: 0.25 * 4 + 0.75 * base 2 = 2.5; y.b: 0.25 * 1 + 0.75 * 3 = 2.5.
        assert_eq!(get(&m, "y.w"), Some(&[2.5f32][..]));
        assert_eq!(get(&m, "y.b"), Some(&[2.5f32][..]));
    }

    #[test]
    fn lambdas_are_renormalised_over_the_owners() {
        // Three parts with 0.2, 0.3, 0.5; layer `z` is owned by parts 1 and 3 only:
        // l' = 0.2 / 0.7 and 0.5 / 0.7. Layer `u` by all three, `n` by none.
        let t = table(
            &[
                ("z.w", vec![0.0], vec![Some(vec![7.0]), None, Some(vec![14.0])]),
                ("u.w", vec![0.0], vec![Some(vec![1.0]), Some(vec![2.0]), Some(vec![3.0])]),
                ("n.w", vec![5.0], vec![None, None, None]),
            ],
            &[&["z.w", "u.w"], &["u.w"], &["z.w", "u.w"]],
        );
        let layers = [layer("n", &["n.w"]), layer("u", &["u.w"]), layer("z", &["z.w"])];
        let m = meld(&t, &layers, &[1, 2, 3], &[0.2, 0.3, 0.5]).expect("melds");
        assert_eq!((m.exclusive, m.overlapping), (0, 2));
        let z = get(&m, "z.w").expect("z")[0] as f64;
        assert!((z - (0.2 * 7.0 + 0.5 * 14.0) / 0.7).abs() < 1e-6, "{z}");
        let u = get(&m, "u.w").expect("u")[0] as f64;
        assert!((u - (0.2 + 0.6 + 1.5)).abs() < 1e-6, "{u}");
        assert!(m.values.iter().all(|(n, _)| n != "n.w"), "a layer nobody owns keeps the base");
        let e = meld(&t, &layers, &[1, 2, 3], &[0.0, 1.0, 0.0]).expect_err("z's owners weigh 0");
        assert!(e.contains("layer `z`"), "{e}");
    }

    /// LoRA rank 1 on a 2x2 weight `W = 0`, scale 2: `dW = 2 * B A`.
    fn lora_table(part2_bias_only: bool) -> (TensorTable, Layer) {
        let w = vec![0.0f32; 4];
        let a = vec![1.0f32, 2.0]; // [1, 2]
        let b = vec![3.0f32, 4.0]; // [2, 1]
        let b2 = vec![1.0f32, -1.0];
        let (provided2, v2b, v2a): (&[&str], _, _) = if part2_bias_only {
            (&["l.bias"], None, None)
        } else {
            (&["l.bias", "l.lora_A.weight", "l.lora_B.weight"], Some(b2), Some(a.clone()))
        };
        let t = table(
            &[
                ("l.weight", w, vec![None, None]),
                ("l.lora_A.weight", vec![0.0; 2], vec![Some(a.clone()), v2a]),
                ("l.lora_B.weight", vec![0.0; 2], vec![Some(b), v2b]),
                ("l.bias", vec![0.0; 2], vec![None, Some(vec![1.0, 1.0])]),
            ],
            &[&["l.lora_A.weight", "l.lora_B.weight"], provided2],
        );
        let lora = Lora {
            weight: "l.weight".into(),
            a: "l.lora_A.weight".into(),
            b: "l.lora_B.weight".into(),
            rank: 1,
            scale: 2.0,
        };
        let layer = Layer { lora: Some(lora), ..layer("l", &["l.bias", "l.lora_A.weight", "l.lora_B.weight"]) };
        (t, layer)
    }

    #[test]
    fn an_overlapping_lora_layer_melds_the_updates_into_the_weight() {
        // Part 2 owns the layer (its bias) but gave no LoRA: it contributes dW = 0, so
        // the update is scaled by part 1's lambda, 0.4 (not 0.4^2 as interpolating A and
        // B separately would give).
        let (t, l) = lora_table(true);
        let m = meld(&t, std::slice::from_ref(&l), &[1, 2], &[0.4, 0.6]).expect("melds");
        // dW_1 = 2 * [3; 4] [1 2] = [6 12; 8 16].
        let want = [6.0 * 0.4, 12.0 * 0.4, 8.0 * 0.4, 16.0 * 0.4];
        let got = get(&m, "l.weight").expect("merged weight");
        for (g, w) in got.iter().zip(want) {
            assert!((*g as f64 - w).abs() < 1e-6, "{got:?} vs {want:?}");
        }
        assert_eq!(get(&m, "l.lora_A.weight"), None, "A and B are the base's zeros");
        assert_eq!(get(&m, "l.lora_B.weight"), None);
        assert_eq!(get(&m, "l.bias"), Some(&[0.6f32, 0.6][..]));
        // Both with LoRA: 0.4 dW_1 + 0.6 dW_2, dW_2 = 2 * [1; -1] [1 2] = [2 4; -2 -4]:
        // no cross terms.
        let (t, l) = lora_table(false);
        let m = meld(&t, &[l], &[1, 2], &[0.4, 0.6]).expect("melds");
        let want = [2.4 + 1.2, 4.8 + 2.4, 3.2 - 1.2, 6.4 - 2.4];
        let got = get(&m, "l.weight").expect("merged weight");
        for (g, w) in got.iter().zip(want) {
            assert!((*g as f64 - w).abs() < 1e-6, "{got:?} vs {want:?}");
        }
    }

    #[test]
    fn a_lora_layer_with_one_owner_keeps_its_a_and_b() {
        // Part 2 provides nothing of layer `l`: not an owner, so part 1's LoRA comes whole.
        let (mut t, l) = lora_table(true);
        t.variants[1].provided.clear();
        let m = meld(&t, &[l], &[1, 2], &[0.4, 0.6]).expect("melds");
        assert_eq!((m.exclusive, m.overlapping), (1, 0));
        assert_eq!(get(&m, "l.lora_A.weight"), Some(&[1.0f32, 2.0][..]));
        assert_eq!(get(&m, "l.lora_B.weight"), Some(&[3.0f32, 4.0][..]));
        assert_eq!(get(&m, "l.weight"), None, "the weight stays the base's");
        assert_eq!(get(&m, "l.bias"), None, "part 1's bias is the base's");
    }
}
