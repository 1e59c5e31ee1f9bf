//! `lower`: turns the graph and its bound weights into the plan's schedule.
//!
//! Walks the graph in topological order and emits one step per node, except where a rule
//! fuses nodes into one step (each rule is named in the plan's step path listing):
//!
//! * `fold_batchnorm`: a BatchNorm whose input is a conv used by nothing else becomes the
//!   conv's per-channel epilogue, `scale = gamma / sqrt(var + eps)`,
//!   `shift = beta - mean * scale (+ conv_bias * scale)`; the conv weight is untouched (so
//!   a variant can later own the affine alone). An unfused BatchNorm becomes a
//!   `ChannelAffine` step with the same scale and shift. Either way the epilogue records
//!   the BatchNorm (`BnInfo`: name, eps, gamma, beta and the folded conv bias, stored as
//!   themselves) so that `adapt-bn` can re-estimate its statistics from the plan.
//! * `fuse_relu`: a ReLU whose input is a conv, linear or channel-affine value used by
//!   nothing else runs in that step's epilogue.
//! * `bias_epilogue`: conv and linear biases are the epilogue's shift.
//!
//! Conv weights are packed for the algorithm the runtime's `conv::choose` picks (at batch
//! size 1), here, once. Folded values are computed in f64 and stored as f32.

use std::collections::{HashMap, HashSet};

use readi_grammar::diag::{Code, Diagnostic, Diagnostics};
use readi_plan::ops::{ChannelAffine, batchnorm_affine};
use readi_runtime::kernels::conv;
use readi_runtime::plan::{
    BnInfo, EpilogueSpec, FORMAT_VERSION, InputSpec, Kernel, Manifest, OutputSpec, ParamSpec, Step, Storage,
    TensorSpec, ValueSpec,
};

use super::buffers::plan_buffers;
use super::weights::Bound;
use crate::ir::{self, Activation, Dim, Graph, NodeId, Op, Pure, SlotKind, ValueRef};

/// A manifest and its tensors, ready to become a plan.
pub struct Lowered {
    pub manifest: Manifest,
    /// One per manifest tensor; empty for a tensor [`lower_only`] did not compute.
    pub tensors: Vec<Vec<f32>>,
    /// For each stored tensor, the parameters (full names) its value derives from.
    pub sources: Vec<Vec<String>>,
}

fn ice(message: String) -> Diagnostics {
    Diagnostics(vec![Diagnostic::error(Code::Internal, format!("internal compiler error while lowering: {message}"))])
}

struct Lowering<'g> {
    graph: &'g Graph,
    bound: &'g Bound<'g>,
    values: Vec<ValueSpec>,
    value_of: HashMap<ValueRef, usize>,
    steps: Vec<Step>,
    tensors: Vec<TensorSpec>,
    data: Vec<Vec<f32>>,
    sources: Vec<Vec<String>>,
    /// Compute only the tensors derived from these parameters (the rest stay empty).
    only: Option<&'g HashSet<String>>,
    tensor_index: HashMap<String, usize>,
    stored_as: HashMap<String, String>,
    /// Number of uses of each node's output (edges plus graph outputs).
    uses: HashMap<NodeId, usize>,
    /// Nodes emitted as part of another node's step, and that node.
    absorbed: HashMap<NodeId, NodeId>,
}

impl<'g> Lowering<'g> {
    fn weight(&self, node: &ir::Node, slot: &str) -> Result<&'g [f32], Diagnostics> {
        let name = ir::join_path(&node.path, slot);
        self.bound.get(&name).copied().ok_or_else(|| ice(format!("weight `{name}` was not bound")))
    }

    /// Adds a stored tensor derived from the parameters `sources`; `data` computes its
    /// value, unless the lowering is restricted to other parameters.
    fn add_tensor(
        &mut self,
        name: String,
        shape: Vec<usize>,
        sources: Vec<String>,
        data: impl FnOnce() -> Vec<f32>,
    ) -> usize {
        if let Some(&i) = self.tensor_index.get(&name) {
            return i;
        }
        let wanted = self.only.is_none_or(|only| sources.iter().any(|s| only.contains(s)));
        self.tensors.push(TensorSpec { name: name.clone(), shape });
        self.data.push(if wanted { data() } else { Vec::new() });
        self.sources.push(sources);
        self.tensor_index.insert(name, self.tensors.len() - 1);
        self.tensors.len() - 1
    }

    fn new_value(&mut self, v: ValueRef, storage: Storage) -> usize {
        let ty = &self.graph.node(v.node).outputs[v.port as usize];
        self.values.push(ValueSpec { shape: ty.shape.clone(), storage });
        self.values.len() - 1
    }

    fn input_value(&self, v: ValueRef) -> Result<usize, Diagnostics> {
        self.value_of
            .get(&v)
            .copied()
            .ok_or_else(|| ice(format!("value of node {} used before it is computed", v.node.index())))
    }

    /// The single user of a node's output, if it has exactly one and is not a graph output.
    fn sole_user(&self, id: NodeId) -> Option<NodeId> {
        let users = self.graph.users(id);
        (self.uses.get(&id) == Some(&1) && users.len() == 1).then(|| users[0])
    }

    /// If the sole user of `id` is a ReLU, absorbs it into `into`'s step and returns true.
    fn absorb_relu(&mut self, id: NodeId, into: NodeId) -> bool {
        match self.sole_user(id) {
            Some(u) if matches!(self.graph.node(u).op, Op::Pure(Pure::Activation(Activation::Relu))) => {
                self.absorbed.insert(u, into);
                true
            }
            _ => false,
        }
    }

    /// Emits a step computing node `id` and every node absorbed into it: they all read the
    /// step's value, and the step's path lists them (`conv1 (+bn1, relu#0)`).
    fn emit(&mut self, id: NodeId, kernel: Kernel, inputs: Vec<usize>) {
        let out = self.new_value(ValueRef { node: id, port: 0 }, Storage::Slot(0));
        let mut absorbed: Vec<NodeId> =
            self.absorbed.iter().filter(|(_, into)| **into == id).map(|(n, _)| *n).collect();
        absorbed.sort();
        let mut path = self.graph.node(id).path.clone();
        if !absorbed.is_empty() {
            let names: Vec<&str> = absorbed.iter().map(|&n| self.graph.node(n).path.as_str()).collect();
            path = format!("{path} (+{})", names.join(", "));
        }
        for n in std::iter::once(id).chain(absorbed) {
            self.value_of.insert(ValueRef { node: n, port: 0 }, out);
        }
        self.steps.push(Step { path, kernel, inputs, output: out });
    }

    /// BatchNorm's folded scale and shift, with an optional preceding bias folded in, and
    /// what AdaBN needs to undo the fold: gamma, beta and that bias, stored as themselves.
    fn fold_bn(
        &mut self,
        bn: NodeId,
        prior_bias: Option<(&[f32], String)>,
    ) -> Result<(usize, usize, BnInfo), Diagnostics> {
        let (prior_bias, prior) = match prior_bias {
            Some((b, name)) => (Some(b), Some(name)),
            None => (None, None),
        };
        let node = self.graph.node(bn);
        let Op::BatchNorm(ir::BatchNorm { channels, eps, .. }) = node.op else {
            return Err(ice("not a batchnorm".into()));
        };
        let (w, b, mean, var) = (
            self.weight(node, "weight")?,
            self.weight(node, "bias")?,
            self.weight(node, "running_mean")?,
            self.weight(node, "running_var")?,
        );
        let c = channels as usize;
        let scale = move || batchnorm_affine(w, b, mean, var, eps, None).0.into_iter().map(|s| s as f32).collect();
        let shift =
            move || batchnorm_affine(w, b, mean, var, eps, prior_bias).1.into_iter().map(|t| t as f32).collect();
        let path = node.path.clone();
        let targets = format!("folded into `{path}@scale`, `{path}@shift`");
        let slots = ["weight", "bias", "running_mean", "running_var"].map(|slot| ir::join_path(&path, slot));
        for name in &slots {
            self.stored_as.insert(name.clone(), targets.clone());
        }
        for name in &slots[..2] {
            self.stored_as.insert(name.clone(), format!("{targets}; kept as `{name}` for adapt-bn"));
        }
        let mut sources = slots.to_vec();
        if let Some(conv) = &prior {
            sources.push(conv.clone());
        }
        let st = self.add_tensor(format!("{path}@scale"), vec![c], slots[..].to_vec(), scale);
        let sh = self.add_tensor(format!("{path}@shift"), vec![c], sources, shift);
        // The records for AdaBN, which runs the base: derived from no parameter a variant
        // changes, so a variant's lowering never recomputes them.
        let [wn, bname, ..] = slots;
        let weight = self.add_tensor(wn, vec![c], Vec::new(), || w.to_vec());
        let bias = self.add_tensor(bname, vec![c], Vec::new(), || b.to_vec());
        let conv_bias = match (prior, prior_bias) {
            (Some(name), Some(pb)) => Some(self.add_tensor(name, vec![c], Vec::new(), || pb.to_vec())),
            _ => None,
        };
        Ok((st, sh, BnInfo { name: path, eps, weight, bias, conv_bias }))
    }

    fn lower_node(&mut self, id: NodeId) -> Result<(), Diagnostics> {
        if self.absorbed.contains_key(&id) {
            return Ok(());
        }
        let g = self.graph;
        let node = g.node(id);
        let inputs: Vec<usize> = g.inputs(id).into_iter().map(|v| self.input_value(v)).collect::<Result<_, _>>()?;
        let shape_of = |v: ValueRef| g.value_type(v).map(|t| t.shape.clone()).unwrap_or_default();
        let known = |d: &Dim| d.as_known().map(|v| v as usize).unwrap_or(1);
        match &node.op {
            Op::Input(_) => {}
            Op::Parameter(ir_param) => {
                let shape = &ir_param.shape;
                let data = self.weight(node, "")?;
                let shape = shape.iter().map(|&d| d as usize).collect();
                let t = self.add_tensor(node.path.clone(), shape, vec![node.path.clone()], || data.to_vec());
                self.stored_as.insert(node.path.clone(), format!("tensor `{}`", node.path));
                let v = self.new_value(ValueRef { node: id, port: 0 }, Storage::Tensor(t));
                self.value_of.insert(ValueRef { node: id, port: 0 }, v);
            }
            Op::Conv2d(c) => {
                let xs = shape_of(g.inputs(id)[0]);
                let s = conv::layer_shape(&c.conv, 1, known(&xs[2]), known(&xs[3]));
                let algo = conv::choose(&s);
                let weight = self.weight(node, "weight")?;
                let len = conv::packed_weight_len(&s, algo);
                let pack = || {
                    let mut packed = vec![0.0; len];
                    conv::pack_weight(&s, algo, weight, &mut packed);
                    packed
                };
                let wname = format!("{}.weight@{}", node.path, algo.name());
                self.stored_as.insert(ir::join_path(&node.path, "weight"), format!("packed as `{wname}`"));
                let wt = self.add_tensor(wname, vec![len], vec![ir::join_path(&node.path, "weight")], pack);
                let bias = if c.bias { Some(self.weight(node, "bias")?) } else { None };
                let mut ep = EpilogueSpec::default();
                let bn = self.sole_user(id).filter(|&u| matches!(g.node(u).op, Op::BatchNorm { .. }));
                if let Some(bn) = bn {
                    let (st, sh, info) = self.fold_bn(bn, bias.map(|b| (b, ir::join_path(&node.path, "bias"))))?;
                    if c.bias {
                        let bname = ir::join_path(&node.path, "bias");
                        let to = format!("folded into `{}@shift`; kept as `{bname}` for adapt-bn", g.node(bn).path);
                        self.stored_as.insert(bname, to);
                    }
                    ep.scale = Some(st);
                    ep.shift = Some(sh);
                    ep.bn = Some(info);
                    self.absorbed.insert(bn, id);
                } else if let Some(b) = bias {
                    let bname = ir::join_path(&node.path, "bias");
                    self.stored_as.insert(bname.clone(), format!("tensor `{bname}`"));
                    ep.shift = Some(self.add_tensor(bname.clone(), vec![b.len()], vec![bname], || b.to_vec()));
                }
                // A ReLU after the conv, or after its folded BatchNorm.
                ep.relu = self.absorb_relu(bn.unwrap_or(id), id);
                let kernel =
                    Kernel::Conv2d { conv: c.conv.clone(), algo: algo.name().to_string(), weight: wt, epilogue: ep };
                self.emit(id, kernel, inputs);
            }
            Op::BatchNorm(bn) => {
                let (st, sh, info) = self.fold_bn(id, None)?;
                let relu = self.absorb_relu(id, id);
                let ep = EpilogueSpec { scale: Some(st), shift: Some(sh), relu, bn: Some(info) };
                let affine = ChannelAffine { channels: bn.channels };
                self.emit(id, Kernel::ChannelAffine { affine, epilogue: ep }, inputs);
            }
            Op::Linear(l) => {
                // Stored transposed, [in, out]: the layout GEMM reads fastest.
                let (fin, fout) = (l.linear.in_features as usize, l.linear.out_features as usize);
                let bias = &l.bias;
                let w = self.weight(node, "weight")?;
                let transpose = || {
                    let mut t = vec![0.0f32; w.len()];
                    for o in 0..fout {
                        for i in 0..fin {
                            t[i * fout + o] = w[o * fin + i];
                        }
                    }
                    t
                };
                let wname = format!("{}.weight@t", node.path);
                self.stored_as.insert(ir::join_path(&node.path, "weight"), format!("transposed as `{wname}`"));
                let wt = self.add_tensor(wname, vec![fin, fout], vec![ir::join_path(&node.path, "weight")], transpose);
                let mut ep = EpilogueSpec::default();
                if *bias {
                    let b = self.weight(node, "bias")?;
                    let bname = ir::join_path(&node.path, "bias");
                    self.stored_as.insert(bname.clone(), format!("tensor `{bname}`"));
                    ep.shift = Some(self.add_tensor(bname.clone(), vec![b.len()], vec![bname], || b.to_vec()));
                }
                ep.relu = self.absorb_relu(id, id);
                let kernel = Kernel::Linear { linear: l.linear.clone(), weight: wt, epilogue: ep };
                self.emit(id, kernel, inputs);
            }
            Op::LayerNorm(ln) => {
                let (mut wt, mut bt) = (None, None);
                let features = &ln.features;
                if ln.affine {
                    for (slot, target) in [("weight", &mut wt), ("bias", &mut bt)] {
                        let data = self.weight(node, slot)?;
                        let name = ir::join_path(&node.path, slot);
                        self.stored_as.insert(name.clone(), format!("tensor `{name}`"));
                        *target =
                            Some(self.add_tensor(name.clone(), vec![*features as usize], vec![name], || data.to_vec()));
                    }
                }
                self.emit(id, Kernel::LayerNorm { norm: ln.clone(), weight: wt, bias: bt }, inputs);
            }
            Op::Pure(p) => self.emit(id, Kernel::Pure(p.clone()), inputs),
        }
        Ok(())
    }
}

/// Lowers a verified graph with all its weights bound.
pub fn lower(graph: &Graph, bound: &Bound<'_>) -> Result<Lowered, Diagnostics> {
    lower_with(graph, bound, None)
}

/// [`lower`], computing only the stored tensors derived from the parameters in `only`;
/// the others are left empty (a variant's lowering: the schedule and tensor table are the
/// base's, and only what the variant changes needs values).
pub fn lower_only(graph: &Graph, bound: &Bound<'_>, only: &HashSet<String>) -> Result<Lowered, Diagnostics> {
    lower_with(graph, bound, Some(only))
}

fn lower_with(graph: &Graph, bound: &Bound<'_>, only: Option<&HashSet<String>>) -> Result<Lowered, Diagnostics> {
    let order = graph.topo_order().ok_or_else(|| ice("the graph has a cycle".into()))?;
    let mut uses: HashMap<NodeId, usize> = HashMap::new();
    for id in graph.node_ids() {
        for v in graph.inputs(id) {
            *uses.entry(v.node).or_default() += 1;
        }
    }
    for o in &graph.outputs {
        *uses.entry(o.value.node).or_default() += 1;
    }
    let mut l = Lowering {
        graph,
        bound,
        values: Vec::new(),
        value_of: HashMap::new(),
        steps: Vec::new(),
        tensors: Vec::new(),
        data: Vec::new(),
        sources: Vec::new(),
        only,
        tensor_index: HashMap::new(),
        stored_as: HashMap::new(),
        uses,
        absorbed: HashMap::new(),
    };
    let mut inputs = Vec::new();
    let mut symbols: Vec<String> = Vec::new();
    for (i, id) in graph.input_nodes().into_iter().enumerate() {
        let node = graph.node(id);
        let Op::Input(a) = &node.op else { continue };
        let v = l.new_value(ValueRef { node: id, port: 0 }, Storage::Input(i));
        l.value_of.insert(ValueRef { node: id, port: 0 }, v);
        for d in &node.outputs[0].shape {
            for s in d.symbols() {
                if !symbols.contains(s) {
                    symbols.push(s.clone());
                }
            }
        }
        inputs.push(InputSpec {
            name: a.name.clone(),
            shape: node.outputs[0].shape.clone(),
            modality: a.modality.clone(),
            optional: a.optional,
            value: v,
        });
    }
    for id in order {
        l.lower_node(id)?;
    }
    let mut outputs = Vec::new();
    for o in &graph.outputs {
        outputs.push(OutputSpec { name: o.name.clone(), value: l.input_value(o.value)? });
    }
    let params = graph
        .param_table()
        .into_iter()
        .map(|(name, _, slot)| ParamSpec {
            shape: slot.shape.iter().map(|&d| d as usize).collect(),
            trainable: slot.kind != SlotKind::Buffer,
            stored_as: l.stored_as.get(&name).cloned().unwrap_or_else(|| "not used by the plan".into()),
            added: slot.kind == SlotKind::Added,
            name,
        })
        .collect();
    let Lowering { mut values, steps, tensors, data, sources, .. } = l;
    let output_values: Vec<usize> = outputs.iter().map(|o: &OutputSpec| o.value).collect();
    let slots = plan_buffers(&mut values, &steps, &output_values);
    let manifest = Manifest {
        format_version: FORMAT_VERSION,
        model: graph.name.clone(),
        model_params: graph.model_params.clone(),
        symbols,
        inputs,
        outputs,
        values,
        steps,
        slots,
        tensors,
        params,
        variants: Vec::new(),
        conditions: None,
    };
    Ok(Lowered { manifest, tensors: data, sources })
}
