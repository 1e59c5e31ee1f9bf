//! `lower`: one kernel step per node, in topological order: the plan's schedule, its
//! stored tensors and its variant tables.
//!
//! A one-to-one map: an input becomes an input value, a `parameter` a stored-tensor
//! value, a conv, transposed conv, conv3d, linear, channel affine, layernorm or groupnorm a
//! kernel reading the tensors its slots name (the epilogue's scale, shift and BatchNorm
//! record included), and every other op the same [`Pure`](readi_plan::ops::Pure)
//! operator as a kernel. The rewrites happened
//! before (fold, fuse, pack); a node they should have changed (an unfolded BatchNorm, an
//! unpacked weight) is a compiler bug. A step's path lists the nodes fused into it
//! (`conv1 (+bn1, relu#0)`). A `conv1d` is its conv2d step between two reshapes to and
//! from `[N, C, 1, L]` (paths `<path> [to N, C, 1, L]` and `<path> [to N, C, L]`).
//!
//! Stored tensors are the ones the steps read, each once, in the order of first use, with
//! the base's values. Each variant's table replaces every tensor whose value under the
//! variant has other bits than the base's; identical replacements (across variants, or
//! equal to a base tensor) are stored once. A replacement counts as added in the budget
//! when its tensor derives from a parameter a rule added. The parameter table says where
//! each of the spec's parameters went. Every value gets a buffer of its own;
//! `plan_buffers` shares them.
//!
//! Assumes every pass before it ran. Changes nothing in the graph.

use std::collections::hash_map::DefaultHasher;
use std::collections::{HashMap, HashSet};
use std::hash::{Hash, Hasher};

use readi_grammar::diag::Diagnostics;
use readi_plan::format::{
    AdapterSpec, BnInfo, EpilogueSpec, FORMAT_VERSION, InputSpec, Kernel, LoraSpec, Manifest, OutputSpec, ParamSpec,
    Replacement, Step, Storage, TensorSpec, ValueSpec, VariantTable,
};

use super::bind_variants::{not_bound, same_bits};
use super::{BackendInputs, Output};
use crate::ir::{Graph, Node, NodeId, Op, ValueRef};
use crate::module::{Lowered, Module};
use crate::ops::Epilogue;
use crate::weights::tensors::{Data, TensorTable};
use half::slice::HalfFloatSliceExt;
use readi_plan::Dim;
use readi_plan::ops::{DType, Pure, Reshape};
use readi_runtime::plan::TensorData;

pub fn run(module: &Module, _: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let table = module.tensors.as_ref().ok_or_else(not_bound)?;
    let g = &module.graph;
    let order = g.topo_order().ok_or_else(|| ice("the graph has a cycle".into()))?;
    let mut l = Lowering {
        graph: g,
        table,
        values: Vec::new(),
        value_of: HashMap::new(),
        steps: Vec::new(),
        names: Vec::new(),
        index: HashMap::new(),
        records: HashSet::new(),
    };
    let mut inputs = Vec::new();
    let mut symbols: Vec<String> = Vec::new();
    for (i, id) in g.input_nodes().into_iter().enumerate() {
        let node = g.node(id);
        let Op::Input(a) = &node.op else { continue };
        let v = l.new_value(ValueRef { node: id, port: 0 }, Storage::Input(i));
        for d in &node.outputs[0].shape {
            for s in d.symbols() {
                if !symbols.contains(s) {
                    symbols.push(s.clone());
                }
            }
        }
        let (name, modality, optional) = (a.name.clone(), a.modality.clone(), a.optional);
        inputs.push(InputSpec { name, shape: node.outputs[0].shape.clone(), modality, optional, value: v });
    }
    for id in order {
        l.lower_node(id)?;
    }
    let mut outputs = Vec::new();
    for o in &g.outputs {
        // The plan's values are f32; an integer or bool output says so for printing.
        let dtype = g.value_type(o.value).map_or(readi_plan::DType::F32, |t| t.dtype);
        outputs.push(OutputSpec { name: o.name.clone(), value: l.value(o.value)?, dtype });
    }
    let Lowering { values, steps, names, records, .. } = l;
    let tensors: Vec<TensorSpec> = names
        .iter()
        .map(|n| TensorSpec::f32(n.clone(), table.get(n).map(|t| t.shape.clone()).unwrap_or_default()))
        .collect();
    let data: Vec<Data> = names
        .iter()
        .map(|n| table.get(n).map(|t| t.base.clone()))
        .collect::<Option<_>>()
        .ok_or_else(|| ice("a stored tensor is not bound".into()))?;
    let params = table
        .params
        .iter()
        .map(|p| ParamSpec {
            name: p.name.clone(),
            shape: p.shape.clone(),
            trainable: p.trainable,
            stored_as: stored_as(&p.name, &names, &records, table),
            added: p.added,
            owned_by: table.owned.get(&p.name).map(|o| o.recorded_scopes()),
        })
        .collect();
    let slots = values.iter().filter(|v| matches!(v.storage, Storage::Slot(_))).count();
    let mut manifest = Manifest {
        format_version: FORMAT_VERSION,
        model: g.name.clone(),
        model_params: g.model_params.clone(),
        symbols,
        inputs,
        outputs,
        values,
        steps,
        slots,
        tensors,
        params,
        variants: Vec::new(),
        conditions: module.variants.clone(),
        footprint: None,
    };
    // The tensors a variant may replace: those a kernel reads or a value stores (not the
    // BatchNorm records, which only AdaBN reads).
    let read = readi_plan::validate::read_tensors(&manifest);
    let mut store = Store::new(std::mem::take(&mut manifest.tensors), data);
    let added: HashSet<&str> = table.owned.iter().filter(|(_, o)| o.added).map(|(n, _)| n.as_str()).collect();
    // Each variant's budget is what it owns: its scope's parameters (a meld: its parts').
    let count = |key: &readi_plan::VariantKey, want: bool| -> u64 {
        table
            .owned_by(key)
            .filter(|(_, o)| o.added == want)
            .map(|(_, o)| o.shape.iter().product::<usize>() as u64)
            .sum()
    };
    // The parameters whose variant values `choose_strategy` stores at half precision
    // (`--variant-f16`): every tensor derived from them alone is stored f16.
    let half: HashSet<&str> = module.strategy.iter().flat_map(|s| &s.half).map(|h| h.param.as_str()).collect();
    for (i, info) in table.variants.iter().enumerate() {
        let mut replaces = Vec::new();
        for (t, name) in names.iter().enumerate() {
            let Some(tensor) = table.get(name) else { continue };
            let Some(Some(value)) = tensor.variants.get(i) else { continue };
            if !read[t] || same_bits(value, &tensor.base) {
                continue;
            }
            let is_half = !half.is_empty()
                && (half.contains(name.as_str())
                    || (!tensor.sources.is_empty() && tensor.sources.iter().all(|s| half.contains(s.as_str()))));
            let dtype = if is_half { DType::F16 } else { DType::F32 };
            let with = store.add(format!("{name}#{}", info.key), &tensor.shape, value.clone(), dtype);
            let is_added = tensor.sources.iter().any(|s| added.contains(s.as_str()));
            replaces.push(Replacement { base: t, with, added: is_added });
        }
        manifest.variants.push(VariantTable {
            key: info.key.clone(),
            replaces,
            tuned_elements: count(&info.key, false),
            added_elements: count(&info.key, true),
            scopes: scope_names(module, &info.key),
            fallback: info.fallback.clone(),
        });
    }
    let data = store
        .data
        .into_iter()
        .zip(&store.specs)
        .map(|(d, spec)| match spec.dtype {
            DType::F16 => {
                let mut h = vec![half::f16::ZERO; d.len()];
                h.convert_from_f32_slice(&d);
                TensorData::F16(h.into())
            }
            _ => TensorData::F32(d),
        })
        .collect();
    manifest.tensors = store.specs;
    Ok(Output::Lowered(Box::new(Lowered { manifest, data })))
}

/// The scoped `adapt` sections whose rules the variant `key` owns (`camera`,
/// `missing=lidar`), in rule order; empty when it owns only unscoped rules.
fn scope_names(module: &Module, key: &readi_plan::VariantKey) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for r in module.adapt.iter().flat_map(|p| &p.rules) {
        if !r.scope.is_all() && r.scope.covers(key) && !out.contains(&r.scope.label()) {
            out.push(r.scope.label());
        }
    }
    out
}

fn ice(message: String) -> Diagnostics {
    super::internal(message)
}

struct Lowering<'m> {
    graph: &'m Graph,
    table: &'m TensorTable,
    values: Vec<ValueSpec>,
    value_of: HashMap<ValueRef, usize>,
    steps: Vec<Step>,
    /// The stored tensors, by name, in the order of first use.
    names: Vec<String>,
    index: HashMap<String, usize>,
    /// Stored tensors only a BatchNorm record reads (AdaBN's, not a kernel's).
    records: HashSet<usize>,
}

impl<'m> Lowering<'m> {
    fn new_value(&mut self, v: ValueRef, storage: Storage) -> usize {
        let shape = self.graph.node(v.node).outputs[v.port as usize].shape.clone();
        let storage = match storage {
            // Every computed value its own buffer, for now.
            Storage::Slot(_) => {
                Storage::Slot(self.values.iter().filter(|v| matches!(v.storage, Storage::Slot(_))).count())
            }
            s => s,
        };
        self.values.push(ValueSpec { shape, storage });
        self.value_of.insert(v, self.values.len() - 1);
        self.values.len() - 1
    }

    fn value(&self, v: ValueRef) -> Result<usize, Diagnostics> {
        self.value_of
            .get(&v)
            .copied()
            .ok_or_else(|| ice(format!("value of node {} used before it is computed", v.node.index())))
    }

    /// The stored tensor a slot of `node` reads.
    fn tensor(&mut self, node: &Node, slot: &str) -> Result<usize, Diagnostics> {
        let s = node
            .params
            .iter()
            .find(|s| s.name == slot)
            .ok_or_else(|| ice(format!("`{}` has no slot `{slot}`", node.path)))?;
        let name = node.param_name(s);
        if self.table.get(&name).is_none() {
            return Err(ice(format!("tensor `{name}` of `{}` is not bound", node.path)));
        }
        if let Some(&i) = self.index.get(&name) {
            return Ok(i);
        }
        self.names.push(name.clone());
        self.index.insert(name, self.names.len() - 1);
        Ok(self.names.len() - 1)
    }

    fn epilogue(&mut self, node: &Node, e: &Epilogue) -> Result<EpilogueSpec, Diagnostics> {
        let scale = if e.scale { Some(self.tensor(node, "scale")?) } else { None };
        let shift = if e.shift { Some(self.tensor(node, "shift")?) } else { None };
        let bn = match &e.bn {
            Some(f) => {
                let weight = self.tensor(node, "bn.weight")?;
                let bias = self.tensor(node, "bn.bias")?;
                let conv_bias = if f.conv_bias { Some(self.tensor(node, "bn.conv_bias")?) } else { None };
                self.records.extend([weight, bias].into_iter().chain(conv_bias));
                Some(BnInfo { name: f.name.clone(), eps: f.eps, weight, bias, conv_bias })
            }
            None => None,
        };
        Ok(EpilogueSpec { scale, shift, act: e.act, bn })
    }

    /// A fused LoRA branch of `rank`: the tensors of its slots; `a_raw` when `A` was left
    /// raw (`pack_weights` packs a conv's `A` only where packing keeps its layout).
    fn lora(&mut self, node: &Node, rank: Option<i64>, a_raw: bool) -> Result<Option<LoraSpec>, Diagnostics> {
        let Some(rank) = rank else { return Ok(None) };
        let rank = usize::try_from(rank).map_err(|_| ice(format!("`{}` has LoRA rank {rank}", node.path)))?;
        Ok(Some(LoraSpec { a: self.tensor(node, "lora_A")?, b: self.tensor(node, "lora_B")?, rank, a_raw }))
    }

    fn lower_node(&mut self, id: NodeId) -> Result<(), Diagnostics> {
        let g = self.graph;
        let node = g.node(id);
        let inputs: Vec<usize> = g.inputs(id).into_iter().map(|v| self.value(v)).collect::<Result<_, _>>()?;
        let kernel = match &node.op {
            Op::Input(_) => return Ok(()),
            Op::Parameter(_)
            | Op::Constant(_)
            | Op::Buffer(crate::ops::BufferOp { dtype: crate::ir::DType::F32, .. }) => {
                let t = self.tensor(node, "")?;
                self.new_value(ValueRef { node: id, port: 0 }, Storage::Tensor(t));
                return Ok(());
            }
            Op::Buffer(_) => return Err(ice(format!("integer buffer `{}` was not folded", node.path))),
            // An index `fold_constants` could not bake (computed from the model's
            // inputs): read at run time, each position checked by the kernel.
            Op::IndexSelect(s) => {
                Kernel::Pure(readi_plan::ops::Pure::IndexSelectAt(readi_plan::ops::IndexSelectAt { axis: s.axis }))
            }
            Op::Conv2d(c) => {
                let algo =
                    c.algo.filter(|_| c.packed).ok_or_else(|| ice(format!("conv `{}` is not packed", node.path)))?;
                if c.bias {
                    return Err(ice(format!("conv `{}` still has a bias", node.path)));
                }
                let weight = self.tensor(node, "weight")?;
                let lora = self.lora(node, c.lora, !algo.packs_as_is() || c.switch)?;
                let epilogue = self.epilogue(node, &c.epilogue)?;
                let adapter = match &c.adapter {
                    Some(a) => {
                        let [dw, db, uw, ub] = crate::ops::AdapterOp::SLOTS;
                        let mid = usize::try_from(a.mid)
                            .map_err(|_| ice(format!("`{}` has an adapter of {} channels", node.path, a.mid)))?;
                        Some(AdapterSpec {
                            down: self.tensor(node, dw)?,
                            down_bias: self.tensor(node, db)?,
                            up: self.tensor(node, uw)?,
                            up_bias: self.tensor(node, ub)?,
                            mid,
                            act: a.act,
                        })
                    }
                    None => None,
                };
                let kernel = Kernel::Conv2d {
                    conv: c.conv.clone(),
                    algo,
                    weight,
                    epilogue,
                    lora,
                    switch: c.switch,
                    adapter,
                    residual: c.residual,
                    channel_scale: c.channel_scale,
                };
                if c.one_d && (c.residual || c.channel_scale) {
                    return Err(ice(format!("conv1d `{}` has a residual or a channel scale", node.path)));
                }
                if c.one_d {
                    return self.lower_conv1d(id, kernel, inputs);
                }
                kernel
            }
            Op::ConvTranspose2d(c) => {
                if c.bias {
                    return Err(ice(format!("conv_transpose2d `{}` still has a bias", node.path)));
                }
                let weight = self.tensor(node, "weight")?;
                Kernel::ConvTranspose2d { conv: c.conv.clone(), weight, epilogue: self.epilogue(node, &c.epilogue)? }
            }
            Op::Conv3d(c) => {
                if c.bias {
                    return Err(ice(format!("conv3d `{}` still has a bias", node.path)));
                }
                let weight = self.tensor(node, "weight")?;
                Kernel::Conv3d { conv: c.conv.clone(), weight, epilogue: self.epilogue(node, &c.epilogue)? }
            }
            Op::Linear(l) => {
                if !l.packed || l.bias {
                    return Err(ice(format!("linear `{}` is not packed or still has a bias", node.path)));
                }
                let weight = self.tensor(node, "weight")?;
                let lora = self.lora(node, l.lora, false)?;
                let (linear, epilogue) = (l.linear.clone(), self.epilogue(node, &l.epilogue)?);
                Kernel::Linear { linear, weight, epilogue, lora, panels: l.panels }
            }
            Op::ChannelAffine(a) => {
                Kernel::ChannelAffine { affine: a.affine.clone(), epilogue: self.epilogue(node, &a.epilogue)? }
            }
            Op::LayerNorm(ln) => {
                let (weight, bias) = if ln.affine {
                    (Some(self.tensor(node, "weight")?), Some(self.tensor(node, "bias")?))
                } else {
                    (None, None)
                };
                Kernel::LayerNorm { norm: ln.clone(), weight, bias }
            }
            Op::GroupNorm(gn) => {
                let (weight, bias) = if gn.affine {
                    (Some(self.tensor(node, "weight")?), Some(self.tensor(node, "bias")?))
                } else {
                    (None, None)
                };
                Kernel::GroupNorm { norm: gn.clone(), weight, bias }
            }
            Op::BatchNorm(_) => return Err(ice(format!("BatchNorm `{}` was not folded", node.path))),
            Op::Pure(p) => Kernel::Pure(p.clone()),
        };
        let output = self.new_value(ValueRef { node: id, port: 0 }, Storage::Slot(0));
        self.steps.push(Step { path: node.display_path(), kernel, inputs, output });
        Ok(())
    }

    /// A conv1d: its conv2d `kernel` between two reshapes, `[N, C, L]` to
    /// `[N, C, 1, L]` and back (each a copy).
    fn lower_conv1d(&mut self, id: NodeId, kernel: Kernel, inputs: Vec<usize>) -> Result<(), Diagnostics> {
        let node = self.graph.node(id);
        let x = *inputs.first().ok_or_else(|| ice(format!("conv1d `{}` has no input", node.path)))?;
        let four_d = |shape: &[Dim]| {
            let mut s = shape.to_vec();
            s.insert(2, Dim::known(1));
            s
        };
        let x4 = four_d(&self.values[x].shape);
        let out = node.outputs[0].shape.clone();
        let (x4, y4) = (self.slot_value(x4), self.slot_value(four_d(&out)));
        let path = node.display_path();
        let reshape = |shape: Vec<Dim>| Kernel::Pure(Pure::Reshape(Reshape { shape }));
        let step = |path: String, kernel, input, output| Step { path, kernel, inputs: vec![input], output };
        self.steps.push(step(format!("{path} [to N, C, 1, L]"), reshape(self.values[x4].shape.clone()), x, x4));
        self.steps.push(step(path.clone(), kernel, x4, y4));
        let output = self.new_value(ValueRef { node: id, port: 0 }, Storage::Slot(0));
        self.steps.push(step(format!("{path} [to N, C, L]"), reshape(out), y4, output));
        Ok(())
    }

    /// A value of `shape` in a buffer of its own that no graph value maps to.
    fn slot_value(&mut self, shape: Vec<Dim>) -> usize {
        let slot = self.values.iter().filter(|v| matches!(v.storage, Storage::Slot(_))).count();
        self.values.push(ValueSpec { shape, storage: Storage::Slot(slot) });
        self.values.len() - 1
    }
}

/// Where a spec parameter went, for the plan's parameter table: `tensor <name>`, or how
/// each stored tensor it contributes to was derived (`packed as ...`, `folded into ...`),
/// and `kept as <name> for adapt-bn` for a BatchNorm record; `not used by the plan`.
fn stored_as(param: &str, names: &[String], records: &HashSet<usize>, table: &TensorTable) -> String {
    let mut groups: Vec<(&str, Vec<&str>)> = Vec::new();
    let mut itself = None;
    for (i, name) in names.iter().enumerate() {
        let Some(t) = table.get(name) else { continue };
        if !t.sources.iter().any(|s| s == param) {
            continue;
        }
        if name == param {
            itself = Some(if records.contains(&i) {
                format!("kept as `{name}` for adapt-bn")
            } else {
                format!("tensor `{name}`")
            });
            continue;
        }
        let how = if t.sources.first().map(String::as_str) == Some(param) {
            t.how.unwrap_or("stored as")
        } else {
            "folded into"
        };
        match groups.iter_mut().find(|(h, _)| *h == how) {
            Some((_, v)) => v.push(name),
            None => groups.push((how, vec![name])),
        }
    }
    let mut parts: Vec<String> = groups
        .into_iter()
        .map(|(how, v)| format!("{how} {}", v.iter().map(|n| format!("`{n}`")).collect::<Vec<_>>().join(", ")))
        .collect();
    parts.extend(itself);
    if parts.is_empty() { "not used by the plan".into() } else { parts.join("; ") }
}

/// The plan's tensors: the base's, then each distinct replacement once.
struct Store {
    specs: Vec<TensorSpec>,
    data: Vec<Data>,
    by_hash: HashMap<u64, Vec<usize>>,
}

fn bits_hash(shape: &[usize], data: &[f32]) -> u64 {
    let mut h = DefaultHasher::new();
    shape.hash(&mut h);
    for v in data {
        v.to_bits().hash(&mut h);
    }
    h.finish()
}

impl Store {
    fn new(specs: Vec<TensorSpec>, data: Vec<Data>) -> Store {
        let mut by_hash: HashMap<u64, Vec<usize>> = HashMap::new();
        for (i, (spec, d)) in specs.iter().zip(&data).enumerate() {
            by_hash.entry(bits_hash(&spec.shape, d)).or_default().push(i);
        }
        Store { specs, data, by_hash }
    }

    /// The index of a stored tensor of this shape and type with `value`'s bits, stored as
    /// `name` when there is none yet (`dtype` f16: converted when the plan is built).
    fn add(&mut self, name: String, shape: &[usize], value: Data, dtype: DType) -> usize {
        let shape = shape.to_vec();
        let h = bits_hash(&shape, &value);
        let found = self.by_hash.get(&h).and_then(|c| {
            c.iter().copied().find(|&j| {
                self.specs[j].shape == shape && self.specs[j].dtype == dtype && same_bits(&self.data[j], &value)
            })
        });
        if let Some(j) = found {
            return j;
        }
        self.specs.push(TensorSpec { name, shape, dtype });
        self.data.push(value);
        let j = self.data.len() - 1;
        self.by_hash.entry(h).or_default().push(j);
        j
    }
}
