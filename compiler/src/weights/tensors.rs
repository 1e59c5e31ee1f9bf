//! The back end's tensor table: every parameter `bind_weights` bound and every tensor a
//! rewrite derived, each with the base model's value and the values of the variants that
//! change it.
//!
//! A node's parameter slot names its tensor (`<path>.<slot>`, or the derived tensor a
//! back-end pass bound to it: a folded scale, a packed weight). Variants are rows of the
//! table, not copies of the graph: a [`Tensor`] holds `variants[i] = Some(value)` where
//! variant `i` differs from the base and `None` where it reads the base's value. A
//! rewrite that derives a tensor from others ([`TensorTable::derive`]) computes it for the
//! base and for exactly the variants in which one of its inputs differs, so a variant
//! costs work and bytes only where it changes something. Values are shared (`Arc`), so
//! moving a tensor through the table copies nothing.
//!
//! Each tensor also records the model parameters it derives from (`sources`, which
//! decide whether a variant's replacement counts as tuned or added in the budget) and how
//! it was derived from its first source (`how`, for the plan's parameter table).

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use readi_plan::VariantKey;

pub use super::variants::Owned;

/// A tensor's values.
pub type Data = Arc<[f32]>;

/// One tensor of the table.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    pub shape: Vec<usize>,
    pub base: Data,
    /// Per variant (index `i` is variant `i + 1` of the plan): its own value, or `None`
    /// where it reads the base's.
    pub variants: Vec<Option<Data>>,
    /// The model parameters the value derives from; a parameter's is itself.
    pub sources: Vec<String>,
    /// How the tensor was derived from its first source (`"packed as"`, `"folded into"`),
    /// `None` for a parameter as bound.
    pub how: Option<&'static str>,
}

impl Tensor {
    /// A bound parameter with no variant values yet.
    pub fn param(name: &str, shape: Vec<usize>, base: Data, variants: usize) -> Tensor {
        Tensor { shape, base, variants: vec![None; variants], sources: vec![name.to_string()], how: None }
    }

    /// The value variant `v` reads (0 is the base).
    pub fn value(&self, v: usize) -> &[f32] {
        match v.checked_sub(1).and_then(|i| self.variants.get(i)) {
            Some(Some(d)) => d,
            _ => &self.base,
        }
    }

    /// Number of elements.
    pub fn numel(&self) -> usize {
        self.shape.iter().product()
    }

    /// Whether some variant has a value of its own.
    pub fn varies(&self) -> bool {
        self.variants.iter().any(Option::is_some)
    }
}

/// The first value that is NaN or infinite, with its index.
pub fn first_non_finite(data: &[f32]) -> Option<(usize, f32)> {
    data.iter().position(|x| !x.is_finite()).map(|i| (i, data[i]))
}

/// A variant of the plan being compiled.
#[derive(Clone, Debug, PartialEq)]
pub struct VariantInfo {
    pub key: VariantKey,
    /// Owned parameters its files did not give; they keep the base value.
    pub fallback: Vec<String>,
    /// The parameters its files gave (for a melded variant, what any of its parts gave):
    /// the tensors it tuned, which decide how a meld treats them.
    pub provided: BTreeSet<String>,
    /// Where its tensors came from, for messages.
    pub origin: String,
}

/// A parameter of the spec, as the plan's parameter table lists it.
#[derive(Clone, Debug, PartialEq)]
pub struct SpecParam {
    pub name: String,
    pub shape: Vec<usize>,
    pub trainable: bool,
    pub added: bool,
}

/// The tensor table: see the module documentation.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TensorTable {
    tensors: BTreeMap<String, Tensor>,
    /// The plan's variants, in plan order (variant `i + 1` is `variants[i]`).
    pub variants: Vec<VariantInfo>,
    /// Every parameter some variant owns, by name; which variants own it is its
    /// [`Owned::scopes`] ([`TensorTable::owns`]).
    pub owned: BTreeMap<String, Owned>,
    /// The spec's parameters (the graph's slots when the weights were bound).
    pub params: Vec<SpecParam>,
}

impl TensorTable {
    pub fn get(&self, name: &str) -> Option<&Tensor> {
        self.tensors.get(name)
    }

    /// Adds or replaces a tensor.
    pub fn insert(&mut self, name: String, tensor: Tensor) {
        self.tensors.insert(name, tensor);
    }

    pub fn iter(&self) -> impl Iterator<Item = (&String, &Tensor)> {
        self.tensors.iter()
    }

    pub fn iter_mut(&mut self) -> impl Iterator<Item = (&String, &mut Tensor)> {
        self.tensors.iter_mut()
    }

    pub fn len(&self) -> usize {
        self.tensors.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tensors.is_empty()
    }

    /// Whether the variant `key` owns the parameter `name` (its rule's scope covers the
    /// key; a meld owns what any of its parts owns; the base owns nothing).
    pub fn owns(&self, key: &VariantKey, name: &str) -> bool {
        self.owned.get(name).is_some_and(|o| o.is_owned_by(key))
    }

    /// Every parameter the variant `key` owns, by name.
    pub fn owned_by<'a>(&'a self, key: &'a VariantKey) -> impl Iterator<Item = (&'a String, &'a Owned)> + 'a {
        super::variants::owned_by(&self.owned, key)
    }

    /// Whether variant `v` of the table (1 is the first; 0 the base) owns `name`.
    pub fn variant_owns(&self, v: usize, name: &str) -> bool {
        v.checked_sub(1).and_then(|i| self.variants.get(i)).is_some_and(|info| self.owns(&info.key, name))
    }

    /// Number of variants (not counting the base).
    pub fn variant_count(&self) -> usize {
        self.variants.len()
    }

    /// The value of `name` under variant `v` (0 is the base).
    pub fn value(&self, name: &str, v: usize) -> Option<&[f32]> {
        self.tensors.get(name).map(|t| t.value(v))
    }

    /// The variants (0 the base, then `1..=variant_count`) in which any of `names` has a
    /// value of its own: where a tensor derived from them must be computed again.
    pub fn varying(&self, names: &[&str]) -> Vec<usize> {
        let mut vs = vec![0];
        for v in 1..=self.variant_count() {
            if names.iter().any(|n| self.tensors.get(*n).is_some_and(|t| t.variants[v - 1].is_some())) {
                vs.push(v);
            }
        }
        vs
    }

    /// Several tensors derived together from `inputs` by `f`, which maps the inputs'
    /// values under one variant to the outputs' values (one per entry of `outputs`, with
    /// that entry's shape). Computed for the base and for each variant in which an input
    /// differs; the outputs' sources are the inputs' sources (in input order, first
    /// occurrence kept).
    pub fn derive(
        &self,
        inputs: &[&str],
        outputs: &[(&'static str, Vec<usize>)],
        f: impl Fn(&[&[f32]]) -> Vec<Vec<f32>>,
    ) -> Result<Vec<Tensor>, String> {
        for n in inputs {
            if !self.tensors.contains_key(*n) {
                return Err(format!("tensor `{n}` is not bound"));
            }
        }
        let values = |v: usize| -> Vec<&[f32]> { inputs.iter().map(|n| self.tensors[*n].value(v)).collect() };
        let compute = |v: usize| -> Result<Vec<Data>, String> {
            let out = f(&values(v));
            if out.len() != outputs.len() {
                return Err(format!("a derivation gave {} tensors for {}", out.len(), outputs.len()));
            }
            let mut data = Vec::with_capacity(out.len());
            for (o, (_, shape)) in out.into_iter().zip(outputs) {
                if o.len() != shape.iter().product::<usize>() {
                    return Err(format!("a derived tensor has {} values for shape {shape:?}", o.len()));
                }
                data.push(Data::from(o));
            }
            Ok(data)
        };
        let base = compute(0)?;
        let mut variants: Vec<Vec<Option<Data>>> = vec![vec![None; self.variant_count()]; outputs.len()];
        for v in self.varying(inputs).into_iter().skip(1) {
            for (k, d) in compute(v)?.into_iter().enumerate() {
                variants[k][v - 1] = Some(d);
            }
        }
        let mut sources: Vec<String> = Vec::new();
        let mut seen = BTreeSet::new();
        for n in inputs {
            for s in &self.tensors[*n].sources {
                if seen.insert(s.clone()) {
                    sources.push(s.clone());
                }
            }
        }
        Ok(outputs
            .iter()
            .zip(base)
            .zip(variants)
            .map(|(((how, shape), base), variants)| Tensor {
                shape: shape.clone(),
                base,
                variants,
                sources: sources.clone(),
                how: Some(how),
            })
            .collect())
    }

    /// Checks that a derived tensor `name` holds only finite values, in the base and in
    /// every variant with a value of its own. The error names the tensor, its sources,
    /// the variant and the cause: a source that is not finite, or else the arithmetic
    /// overflowing f32, with the source value of largest magnitude (which is usually
    /// what overflowed).
    pub fn check_finite(&self, name: &str, t: &Tensor) -> Result<(), String> {
        for v in 0..=t.variants.len() {
            if v > 0 && t.variants[v - 1].is_none() {
                continue;
            }
            let Some((i, x)) = first_non_finite(t.value(v)) else { continue };
            let sources: Vec<String> = t.sources.iter().map(|s| format!("`{s}`")).collect();
            let variant = match v.checked_sub(1).and_then(|i| self.variants.get(i)) {
                Some(info) => format!(" in variant `{}`", info.key),
                None => String::new(),
            };
            let mut largest: Option<(&str, usize, f32)> = None;
            let mut cause = None;
            for s in &t.sources {
                let Some(src) = self.value(s, v) else { continue };
                if let Some((j, y)) = first_non_finite(src) {
                    cause = Some(format!("its source `{s}[{j}]` = {y}"));
                    break;
                }
                for (j, &y) in src.iter().enumerate() {
                    if largest.is_none_or(|(_, _, l)| y.abs() > l.abs()) {
                        largest = Some((s.as_str(), j, y));
                    }
                }
            }
            let cause = cause.unwrap_or_else(|| match largest {
                Some((s, j, y)) => {
                    format!("the arithmetic overflows f32 (the largest source value is `{s}[{j}]` = {y:e})")
                }
                None => "the arithmetic overflows f32".to_string(),
            });
            return Err(format!(
                "derived tensor `{name}`{variant} is {x} at flat index {i}: {cause}; it derives from {}",
                sources.join(", ")
            ));
        }
        Ok(())
    }

    /// One tensor derived from `inputs` by `f` (see [`derive`](TensorTable::derive)).
    pub fn derive_one(
        &self,
        inputs: &[&str],
        how: &'static str,
        shape: Vec<usize>,
        f: impl Fn(&[&[f32]]) -> Vec<f32>,
    ) -> Result<Tensor, String> {
        let mut t = self.derive(inputs, &[(how, shape)], |x| vec![f(x)])?;
        Ok(t.remove(0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn table() -> TensorTable {
        let variants = (0..3)
            .map(|i| VariantInfo {
                key: VariantKey::level("fog", i as f64 + 1.0),
                fallback: Vec::new(),
                provided: BTreeSet::new(),
                origin: String::new(),
            })
            .collect();
        let mut t = TensorTable { variants, ..TensorTable::default() };
        let mut a = Tensor::param("a", vec![2], Data::from(vec![1.0, 2.0]), 3);
        a.variants[1] = Some(Data::from(vec![10.0, 20.0]));
        t.insert("a".into(), a);
        let mut b = Tensor::param("b", vec![2], Data::from(vec![3.0, 4.0]), 3);
        b.variants[2] = Some(Data::from(vec![30.0, 40.0]));
        t.insert("b".into(), b);
        t.insert("c".into(), Tensor::param("c", vec![2], Data::from(vec![5.0, 6.0]), 3));
        t
    }

    #[test]
    fn derived_tensors_are_computed_where_an_input_varies() {
        let t = table();
        let sum =
            t.derive_one(&["a", "b"], "summed into", vec![2], |x| x[0].iter().zip(x[1]).map(|(p, q)| p + q).collect());
        let sum = sum.expect("derives");
        assert_eq!(&*sum.base, &[4.0, 6.0]);
        // Variant 1 changes neither input: it reads the base. Variant 2 changes `a`,
        // variant 3 changes `b`.
        assert_eq!(sum.variants[0], None);
        assert_eq!(sum.value(2), &[13.0, 24.0]);
        assert_eq!(sum.value(3), &[31.0, 42.0]);
        assert_eq!(sum.sources, vec!["a".to_string(), "b".to_string()]);
        // A tensor of an input that never varies varies nowhere.
        let c2 = t.derive_one(&["c"], "doubled into", vec![2], |x| x[0].iter().map(|v| 2.0 * v).collect());
        assert!(!c2.expect("derives").varies());
    }

    #[test]
    fn derivations_are_checked() {
        let t = table();
        assert!(t.derive_one(&["zz"], "x", vec![2], |x| x[0].to_vec()).is_err());
        assert!(t.derive_one(&["a"], "x", vec![3], |x| x[0].to_vec()).is_err());
    }
}
