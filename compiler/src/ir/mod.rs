//! The graph IR.
//!
//! A model is a directed acyclic graph ([`Graph`]) on a petgraph `StableDiGraph`:
//!
//! * **Nodes** ([`Node`]) are operations. A node holds its [`Op`] with typed attributes,
//!   its dotted **path** (`layer1.0.conv1`), which is also the prefix of its parameters'
//!   PyTorch `state_dict` keys, its **parameter slots** ([`ParamSlot`]: name, shape, dtype;
//!   the values are bound in a later stage), the [`TensorType`] of each output, the
//!   [`ScopeId`] of the block instance or namespace it was created in, and the source
//!   [`Span`] of the expression that created it.
//! * **Edges** ([`Edge`]) carry tensors: from output port `src_port` of one node to input
//!   port `dst_port` of another. A node's inputs are its incoming edges ordered by
//!   `dst_port`, which run `0..arity` without gaps.
//! * **Graph inputs** are nodes whose op is [`Op::Input`]; **graph outputs** are named
//!   references to node outputs ([`GraphOutput`]).
//! * **Scopes** ([`ScopeInfo`]) form a side table: the model, each block instance, each
//!   `seq`, list and namespace, with its path and parent. Adaptation selectors such as
//!   "every BatchNorm in a `BasicBlock`" are answered from it.
//!
//! Ids are newtypes ([`NodeId`], [`ScopeId`]) so a node index cannot be mistaken for
//! anything else. Node ids stay valid when other nodes are removed (stable graph); the
//! text printer renumbers nodes in topological order, so printed ids carry no history.
//!
//! Shapes are lists of [`Dim`]: known sizes or products with symbolic factors (the batch
//! dimension `N`). Every node's output types are inferred when it is created (see
//! [`crate::infer`]) and re-checked by the verifier ([`crate::verify`]).

mod op;

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use petgraph::Direction;
use petgraph::stable_graph::{NodeIndex, StableDiGraph};
use petgraph::visit::EdgeRef;
use readi_grammar::diag::Span;
pub use readi_plan::ops::{
    Activation, BatchNorm, BinaryOp, Conv2d, LayerNorm, Linear, Pool2d, PoolKind, Pure, Scalar, Upsample, UpsampleMode,
    Window2,
};
pub use readi_plan::{DType, Dim, TensorType};

pub use op::*;

/// The identity of a node. Stays valid while other nodes are added and removed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct NodeId(NodeIndex<u32>);

impl NodeId {
    /// The raw index, for stable ordering and display.
    pub fn index(self) -> usize {
        self.0.index()
    }
}

/// The identity of a scope in [`Graph::scopes`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ScopeId(pub u32);

/// One output of one node: what an edge carries and what an op consumes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ValueRef {
    pub node: NodeId,
    pub port: u16,
}

/// A tensor edge from `src_port` of its source node to `dst_port` of its target node.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Edge {
    pub src_port: u16,
    pub dst_port: u16,
}

/// An operation in the graph.
#[derive(Clone, Debug, PartialEq)]
pub struct Node {
    pub op: Op,
    /// Dotted path; the `state_dict` prefix of the node's parameters. Nodes the source
    /// did not name get a segment `<op>#<k>` (for example `layer1.0.relu#1`).
    pub path: String,
    pub scope: ScopeId,
    pub params: Vec<ParamSlot>,
    pub outputs: Vec<TensorType>,
    pub span: Span,
    /// The paths of the nodes a back-end fusion merged into this one (a folded BatchNorm,
    /// an absorbed ReLU), for listings: `conv1 (+bn1, relu#0)`.
    pub fused: Vec<String>,
}

impl Node {
    /// A node with no fused nodes.
    pub fn new(
        op: Op,
        path: String,
        scope: ScopeId,
        params: Vec<ParamSlot>,
        outputs: Vec<TensorType>,
        span: Span,
    ) -> Node {
        Node { op, path, scope, params, outputs, span, fused: Vec::new() }
    }

    /// The full name of the tensor a parameter slot reads: `<path>.<slot>`, or the tensor
    /// a back-end pass bound it to.
    pub fn param_name(&self, slot: &ParamSlot) -> String {
        slot.tensor.clone().unwrap_or_else(|| join_path(&self.path, slot.name))
    }

    /// The path with the fused nodes, as step listings show it: `conv1 (+bn1, relu#0)`.
    pub fn display_path(&self) -> String {
        if self.fused.is_empty() { self.path.clone() } else { format!("{} (+{})", self.path, self.fused.join(", ")) }
    }
}

/// What kind of construct opened a scope.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ScopeKind {
    /// The model itself (path `""`).
    Model,
    /// An instance of a block.
    Block(String),
    /// The items of a `seq`.
    Seq,
    /// The elements of a list of instances.
    List,
    /// A `name { ... }` namespace.
    Namespace,
}

/// A block instance, `seq`, list or namespace.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ScopeInfo {
    pub path: String,
    pub kind: ScopeKind,
    pub parent: Option<ScopeId>,
    pub span: Span,
}

/// A named output of the model.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct GraphOutput {
    pub name: String,
    pub value: ValueRef,
    pub span: Span,
}

/// A model as a graph of operations. See the module documentation.
#[derive(Clone, Debug)]
pub struct Graph {
    /// The model's name.
    pub name: String,
    /// The model's parameters after defaults and overrides, for the record.
    pub model_params: Vec<(String, String)>,
    graph: StableDiGraph<Node, Edge, u32>,
    pub outputs: Vec<GraphOutput>,
    pub scopes: Vec<ScopeInfo>,
}

/// Joins two path pieces with a dot, leaving out empty ones.
pub fn join_path(prefix: &str, name: &str) -> String {
    match (prefix.is_empty(), name.is_empty()) {
        (true, _) => name.to_string(),
        (_, true) => prefix.to_string(),
        _ => format!("{prefix}.{name}"),
    }
}

impl Graph {
    /// An empty graph with the model scope.
    pub fn new(name: impl Into<String>, span: Span) -> Graph {
        Graph {
            name: name.into(),
            model_params: Vec::new(),
            graph: StableDiGraph::default(),
            outputs: Vec::new(),
            scopes: vec![ScopeInfo { path: String::new(), kind: ScopeKind::Model, parent: None, span }],
        }
    }

    /// The model's root scope.
    pub fn root_scope(&self) -> ScopeId {
        ScopeId(0)
    }

    /// Adds a scope and returns its id.
    pub fn add_scope(&mut self, info: ScopeInfo) -> ScopeId {
        self.scopes.push(info);
        ScopeId(self.scopes.len() as u32 - 1)
    }

    pub fn scope(&self, id: ScopeId) -> &ScopeInfo {
        &self.scopes[id.0 as usize]
    }

    /// The scope and its ancestors, innermost first.
    pub fn scope_chain(&self, id: ScopeId) -> impl Iterator<Item = &ScopeInfo> {
        let mut cur = Some(id);
        std::iter::from_fn(move || {
            let s = self.scopes.get(cur?.0 as usize)?;
            cur = s.parent;
            Some(s)
        })
    }

    /// Adds a node with its inputs; `inputs[i]` becomes input port `i`.
    pub fn add_node(&mut self, node: Node, inputs: &[ValueRef]) -> NodeId {
        let id = NodeId(self.graph.add_node(node));
        for (port, v) in inputs.iter().enumerate() {
            self.graph.add_edge(v.node.0, id.0, Edge { src_port: v.port, dst_port: port as u16 });
        }
        id
    }

    /// Removes a node and its edges.
    pub fn remove_node(&mut self, id: NodeId) -> Option<Node> {
        self.graph.remove_node(id.0)
    }

    /// Points every use of `old` (edges and graph outputs) at `new`.
    pub fn replace_uses(&mut self, old: ValueRef, new: ValueRef) {
        self.redirect(old, new, None);
    }

    /// Points every use of `old` at `new`, except uses by `keep` (which goes on reading
    /// `old`): how a pass wraps a value, `y -> add(y, branch)`.
    pub fn replace_uses_except(&mut self, old: ValueRef, new: ValueRef, keep: NodeId) {
        self.redirect(old, new, Some(keep));
    }

    fn redirect(&mut self, old: ValueRef, new: ValueRef, keep: Option<NodeId>) {
        let uses: Vec<_> = self
            .graph
            .edges_directed(old.node.0, Direction::Outgoing)
            .filter(|e| e.weight().src_port == old.port && Some(NodeId(e.target())) != keep)
            .map(|e| (e.id(), e.target(), e.weight().dst_port))
            .collect();
        for (eid, target, dst_port) in uses {
            self.graph.remove_edge(eid);
            self.graph.add_edge(new.node.0, target, Edge { src_port: new.port, dst_port });
        }
        for o in &mut self.outputs {
            if o.value == old {
                o.value = new;
            }
        }
    }

    /// Removes every incoming edge of `node`: a node that became a constant reads nothing.
    pub fn detach_inputs(&mut self, node: NodeId) {
        let old: Vec<_> = self.graph.edges_directed(node.0, Direction::Incoming).map(|e| e.id()).collect();
        for e in old {
            self.graph.remove_edge(e);
        }
    }

    /// Makes input port `port` of `node` read `value` instead of what it read.
    pub fn set_input(&mut self, node: NodeId, port: u16, value: ValueRef) {
        let old: Vec<_> = self
            .graph
            .edges_directed(node.0, Direction::Incoming)
            .filter(|e| e.weight().dst_port == port)
            .map(|e| e.id())
            .collect();
        for e in old {
            self.graph.remove_edge(e);
        }
        self.graph.add_edge(value.node.0, node.0, Edge { src_port: value.port, dst_port: port });
    }

    pub fn node(&self, id: NodeId) -> &Node {
        &self.graph[id.0]
    }

    pub fn node_mut(&mut self, id: NodeId) -> &mut Node {
        &mut self.graph[id.0]
    }

    pub fn contains(&self, id: NodeId) -> bool {
        self.graph.contains_node(id.0)
    }

    pub fn node_count(&self) -> usize {
        self.graph.node_count()
    }

    /// All node ids in creation order.
    pub fn node_ids(&self) -> impl Iterator<Item = NodeId> + '_ {
        self.graph.node_indices().map(NodeId)
    }

    /// The type of a value.
    pub fn value_type(&self, v: ValueRef) -> Option<&TensorType> {
        self.graph.node_weight(v.node.0)?.outputs.get(v.port as usize)
    }

    /// The inputs of a node in port order.
    pub fn inputs(&self, id: NodeId) -> Vec<ValueRef> {
        let mut edges: Vec<(u16, ValueRef)> = self
            .graph
            .edges_directed(id.0, Direction::Incoming)
            .map(|e| (e.weight().dst_port, ValueRef { node: NodeId(e.source()), port: e.weight().src_port }))
            .collect();
        edges.sort_by_key(|(p, _)| *p);
        edges.into_iter().map(|(_, v)| v).collect()
    }

    /// The raw incoming edges of a node: `(dst_port, source value)`, unsorted.
    pub fn incoming(&self, id: NodeId) -> Vec<(u16, ValueRef)> {
        self.graph
            .edges_directed(id.0, Direction::Incoming)
            .map(|e| (e.weight().dst_port, ValueRef { node: NodeId(e.source()), port: e.weight().src_port }))
            .collect()
    }

    /// How many times the outputs of `id` are read: one per edge, one per graph output.
    pub fn uses(&self, id: NodeId) -> usize {
        let edges = self.graph.edges_directed(id.0, Direction::Outgoing).count();
        edges + self.outputs.iter().filter(|o| o.value.node == id).count()
    }

    /// The nodes that consume any output of `id`.
    pub fn users(&self, id: NodeId) -> Vec<NodeId> {
        let mut v: Vec<NodeId> = self.graph.neighbors_directed(id.0, Direction::Outgoing).map(NodeId).collect();
        v.sort();
        v.dedup();
        v
    }

    /// Graph input nodes in creation order.
    pub fn input_nodes(&self) -> Vec<NodeId> {
        self.node_ids().filter(|&n| matches!(self.node(n).op, Op::Input(_))).collect()
    }

    /// A topological order that follows creation order wherever dependencies allow, so it
    /// is stable and reads like the source. `None` if the graph has a cycle.
    pub fn topo_order(&self) -> Option<Vec<NodeId>> {
        let mut indegree: std::collections::HashMap<NodeIndex<u32>, usize> =
            self.graph.node_indices().map(|n| (n, self.graph.edges_directed(n, Direction::Incoming).count())).collect();
        let mut ready: BinaryHeap<Reverse<NodeIndex<u32>>> =
            indegree.iter().filter(|(_, d)| **d == 0).map(|(n, _)| Reverse(*n)).collect();
        let mut order = Vec::with_capacity(self.graph.node_count());
        while let Some(Reverse(n)) = ready.pop() {
            order.push(NodeId(n));
            for e in self.graph.edges_directed(n, Direction::Outgoing) {
                if let Some(d) = indegree.get_mut(&e.target()) {
                    *d -= 1;
                    if *d == 0 {
                        ready.push(Reverse(e.target()));
                    }
                }
            }
        }
        (order.len() == self.graph.node_count()).then_some(order)
    }

    /// Every parameter slot as `(full name, node, slot)`, in topological order.
    pub fn param_table(&self) -> Vec<(String, NodeId, &ParamSlot)> {
        let order = self.topo_order().unwrap_or_else(|| self.node_ids().collect());
        let mut out = Vec::new();
        for id in order {
            let node = self.node(id);
            for slot in &node.params {
                out.push((node.param_name(slot), id, slot));
            }
        }
        out
    }

    /// Total number of trainable parameters (PyTorch's `sum(p.numel() for p in
    /// model.parameters())`).
    pub fn parameter_count(&self) -> u64 {
        self.param_table().iter().filter(|(_, _, s)| s.kind == SlotKind::Param).map(|(_, _, s)| s.numel()).sum()
    }
}
