//! The typed syntax tree of a `.readi` file.
//!
//! Every node carries the [`Span`] of the source text it came from, so later stages (the
//! elaborator, the verifier, the adaptation resolver) can point at the exact place. The tree
//! is plain data: no interning, no ids; it is small and built once per file.

use crate::diag::Span;

/// A parsed `.readi` file.
#[derive(Clone, Debug, PartialEq)]
pub struct SourceFile {
    pub items: Vec<Item>,
}

impl SourceFile {
    /// The `model` items of the file (a valid file has exactly one).
    pub fn models(&self) -> impl Iterator<Item = &ModelDef> {
        self.items.iter().filter_map(|i| match i {
            Item::Model(m) => Some(m),
            _ => None,
        })
    }
    /// The `use` declarations of the file.
    pub fn uses(&self) -> impl Iterator<Item = &UseDecl> {
        self.items.iter().filter_map(|i| match i {
            Item::Use(u) => Some(u),
            _ => None,
        })
    }
    /// The `block` definitions of the file.
    pub fn blocks(&self) -> impl Iterator<Item = &BlockDef> {
        self.items.iter().filter_map(|i| match i {
            Item::Block(b) => Some(b),
            _ => None,
        })
    }
    /// The `adapt` sections of the file, unscoped and scoped (`adapt camera { ... }`).
    pub fn adapt_sections(&self) -> impl Iterator<Item = &AdaptSection> {
        self.items.iter().filter_map(|i| match i {
            Item::Adapt(a) => Some(a),
            _ => None,
        })
    }
    /// The `variants` sections of the file (a valid file has at most one).
    pub fn variant_sections(&self) -> impl Iterator<Item = &VariantSection> {
        self.items.iter().filter_map(|i| match i {
            Item::Variants(v) => Some(v),
            _ => None,
        })
    }
}

/// A top-level item.
#[derive(Clone, Debug, PartialEq)]
pub enum Item {
    Use(UseDecl),
    Block(BlockDef),
    Model(ModelDef),
    Adapt(AdaptSection),
    Variants(VariantSection),
}

/// `use "path.readi"`: another file's items, by a path relative to this file.
#[derive(Clone, Debug, PartialEq)]
pub struct UseDecl {
    pub path: String,
    pub span: Span,
}

/// A name with its place in the source.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct Ident {
    pub name: String,
    pub span: Span,
}

/// `block Name(params) { body }`.
#[derive(Clone, Debug, PartialEq)]
pub struct BlockDef {
    pub name: Ident,
    pub params: Vec<Param>,
    pub body: Body,
    pub span: Span,
}

/// `model name(params) { body }`.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelDef {
    pub name: Ident,
    pub params: Vec<Param>,
    pub body: Body,
    pub span: Span,
}

/// A formal parameter of a block or model.
#[derive(Clone, Debug, PartialEq)]
pub struct Param {
    pub name: Ident,
    pub ty: Option<(TypeName, Span)>,
    pub default: Option<Expr>,
    pub span: Span,
}

/// The declared type of a parameter.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TypeName {
    Tensor,
    Int,
    Float,
    Bool,
    Str,
    List,
}

impl TypeName {
    pub fn as_str(self) -> &'static str {
        match self {
            TypeName::Tensor => "tensor",
            TypeName::Int => "int",
            TypeName::Float => "float",
            TypeName::Bool => "bool",
            TypeName::Str => "str",
            TypeName::List => "list",
        }
    }
}

/// `{ statements }`.
#[derive(Clone, Debug, PartialEq)]
pub struct Body {
    pub stmts: Vec<Stmt>,
    pub span: Span,
}

/// A statement with its span.
#[derive(Clone, Debug, PartialEq)]
pub struct Stmt {
    pub kind: StmtKind,
    pub span: Span,
}

/// The statements of a body.
#[derive(Clone, Debug, PartialEq)]
pub enum StmtKind {
    /// `input name: dtype[dims] @modality optional`.
    Input(InputDecl),
    /// `output name [= value]`.
    Output { name: Ident, value: Option<Expr> },
    /// `let name = value`.
    Let { name: Ident, value: Expr },
    /// `if c { } else if c { } else { }`.
    If { branches: Vec<(Expr, Body)>, otherwise: Option<Body> },
    /// `return value`.
    Return(Expr),
    /// `name { body }`: a namespace.
    Scope { name: LayerName, body: Body },
    /// `name = value`: a named layer, instance or list of instances.
    Named { name: LayerName, value: Expr },
}

/// `input image: f32[N, 3, 224, 224] @camera optional`.
#[derive(Clone, Debug, PartialEq)]
pub struct InputDecl {
    pub name: Ident,
    pub dtype: (DType, Span),
    pub dims: Vec<Expr>,
    pub modality: Option<Ident>,
    pub optional: bool,
}

/// Element types of tensors.
/// Element types, shared with the compiler and the plan format.
pub use readi_plan::DType;

/// One segment of a layer path: `conv1`, `0`, `"block1-0"` or `"block{i}-{j}"`.
#[derive(Clone, Debug, PartialEq)]
pub enum LayerName {
    Ident(Ident),
    Index(u64, Span),
    /// A quoted name; its text is known once its `{expr}` parts are evaluated.
    Quoted(QuotedName),
}

/// `"block{i}-{j}"`: literal text and interpolated expressions, in order.
#[derive(Clone, Debug, PartialEq)]
pub struct QuotedName {
    pub parts: Vec<NamePart>,
    /// The text between the quotes, as written (for printing).
    pub source: String,
    pub span: Span,
}

/// A piece of a quoted name.
#[derive(Clone, Debug, PartialEq)]
pub enum NamePart {
    Text(String),
    /// `{expr}`: replaced by the value of `expr`, an int or a string.
    Expr(Expr),
}

/// Why `text` cannot be one segment of a layer path, if it cannot: segments are joined
/// by `.` into state_dict keys, and `#` marks the names readi gives unnamed layers.
pub fn bad_layer_name(text: &str) -> Option<&'static str> {
    if text.is_empty() {
        Some("a layer name cannot be empty")
    } else if text.contains('.') {
        Some("a layer name cannot contain `.`: it separates the segments of a path")
    } else if text.contains('#') {
        Some("a layer name cannot contain `#`: it marks the names of unnamed layers")
    } else {
        None
    }
}

impl QuotedName {
    /// The name's text when it has no `{expr}` parts.
    pub fn literal(&self) -> Option<String> {
        let mut out = String::new();
        for p in &self.parts {
            match p {
                NamePart::Text(t) => out.push_str(t),
                NamePart::Expr(_) => return None,
            }
        }
        Some(out)
    }
}

impl LayerName {
    pub fn span(&self) -> Span {
        match self {
            LayerName::Ident(i) => i.span,
            LayerName::Index(_, s) => *s,
            LayerName::Quoted(q) => q.span,
        }
    }
    /// The name as a path segment when it needs no evaluation; a quoted name with `{expr}`
    /// parts gives its source text (the elaborator evaluates it instead).
    pub fn text(&self) -> String {
        match self {
            LayerName::Ident(i) => i.name.clone(),
            LayerName::Index(n, _) => n.to_string(),
            LayerName::Quoted(q) => q.literal().unwrap_or_else(|| q.source.clone()),
        }
    }
    /// The name as written in source: quoted names with their quotes.
    pub fn source(&self) -> String {
        match self {
            LayerName::Quoted(q) => format!("\"{}\"", q.source),
            _ => self.text(),
        }
    }
}

/// An expression with its span.
#[derive(Clone, Debug, PartialEq)]
pub struct Expr {
    pub kind: ExprKind,
    pub span: Span,
}

/// One entry of a tensor subscript `x[...]`.
#[derive(Clone, Debug, PartialEq)]
pub enum Subscript {
    /// An index: removes its axis.
    Index(Expr),
    /// `start:stop:step`, each part optional.
    Range { start: Option<Expr>, stop: Option<Expr>, step: Option<Expr>, span: Span },
    /// `...`.
    Ellipsis(Span),
}

impl Subscript {
    pub fn span(&self) -> Span {
        match self {
            Subscript::Index(e) => e.span,
            Subscript::Range { span, .. } | Subscript::Ellipsis(span) => *span,
        }
    }
}

/// Expression forms.
#[derive(Clone, Debug, PartialEq)]
pub enum ExprKind {
    Int(i64),
    Float(f64),
    Bool(bool),
    Str(String),
    /// A name: a value in scope, or (unbound, in an input shape) a symbolic dimension.
    Var(Ident),
    Unary(UnaryOp, Box<Expr>),
    Binary(BinaryOp, Box<Expr>, Box<Expr>),
    /// `callee(args)`: an op, a block or a builtin function.
    Call {
        callee: Ident,
        args: Vec<Arg>,
    },
    /// `base.name`: a named layer inside an instance or namespace.
    Member(Box<Expr>, LayerName),
    /// `base[index]`.
    Index(Box<Expr>, Box<Expr>),
    /// `base[a:b:s, ..., i]`: a tensor slice (any index with a `:`, `...`, a comma).
    Subscript(Box<Expr>, Vec<Subscript>),
    /// `[a, b, c]`.
    List(Vec<Expr>),
    /// `[elem for var in start..end]`.
    Comprehension {
        elem: Box<Expr>,
        var: Ident,
        start: Box<Expr>,
        end: Box<Expr>,
    },
    /// `if cond then a else b`.
    IfElse {
        cond: Box<Expr>,
        then: Box<Expr>,
        otherwise: Box<Expr>,
    },
    /// `seq(input) { items }`.
    Seq {
        input: Box<Expr>,
        items: Vec<SeqItem>,
    },
}

/// A call argument, positional or `name = value`.
#[derive(Clone, Debug, PartialEq)]
pub struct Arg {
    pub name: Option<Ident>,
    pub value: Expr,
    pub span: Span,
}

/// An item of a `seq` body.
#[derive(Clone, Debug, PartialEq)]
pub enum SeqItem {
    /// `[name =] callee[(args)]`; the previous item's output is passed as first argument.
    Call { name: Option<LayerName>, callee: Ident, args: Vec<Arg>, span: Span },
    /// `for var in start..end { items }`.
    For { var: Ident, start: Expr, end: Expr, items: Vec<SeqItem>, span: Span },
    /// `if c { items } else if c { items } else { items }`.
    If { branches: Vec<(Expr, Vec<SeqItem>)>, otherwise: Option<Vec<SeqItem>>, span: Span },
}

/// Prefix operators.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum UnaryOp {
    Neg,
    Not,
}

/// Infix operators.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BinaryOp {
    Or,
    And,
    Eq,
    Ne,
    Lt,
    Le,
    Gt,
    Ge,
    Add,
    Sub,
    Mul,
    Div,
    FloorDiv,
    Mod,
    Pow,
}

impl BinaryOp {
    /// Binding power: higher binds tighter.
    pub fn precedence(self) -> u8 {
        match self {
            BinaryOp::Or => 1,
            BinaryOp::And => 2,
            BinaryOp::Eq | BinaryOp::Ne | BinaryOp::Lt | BinaryOp::Le | BinaryOp::Gt | BinaryOp::Ge => 3,
            BinaryOp::Add | BinaryOp::Sub => 4,
            BinaryOp::Mul | BinaryOp::Div | BinaryOp::FloorDiv | BinaryOp::Mod => 5,
            BinaryOp::Pow => 6,
        }
    }
    /// `**` associates to the right, everything else to the left.
    pub fn right_assoc(self) -> bool {
        self == BinaryOp::Pow
    }
    pub fn as_str(self) -> &'static str {
        match self {
            BinaryOp::Or => "or",
            BinaryOp::And => "and",
            BinaryOp::Eq => "==",
            BinaryOp::Ne => "!=",
            BinaryOp::Lt => "<",
            BinaryOp::Le => "<=",
            BinaryOp::Gt => ">",
            BinaryOp::Ge => ">=",
            BinaryOp::Add => "+",
            BinaryOp::Sub => "-",
            BinaryOp::Mul => "*",
            BinaryOp::Div => "/",
            BinaryOp::FloorDiv => "//",
            BinaryOp::Mod => "%",
            BinaryOp::Pow => "**",
        }
    }
}

// -------------------------------------------------------------------------------------
// Adaptation section
// -------------------------------------------------------------------------------------

/// `adapt { rules }`, or `adapt camera, missing=lidar { rules }`.
#[derive(Clone, Debug, PartialEq)]
pub struct AdaptSection {
    /// The variants the rules belong to; empty: every variant.
    pub scopes: Vec<AdaptScope>,
    pub rules: Vec<AdaptRule>,
    pub span: Span,
}

/// One scope of a section: `camera` (a modality), `fog` (an axis), `missing`, or
/// `missing=lidar` (`name=value`).
#[derive(Clone, Debug, PartialEq)]
pub struct AdaptScope {
    pub name: Ident,
    pub value: Option<Ident>,
    pub span: Span,
}

impl AdaptScope {
    /// The scope as written: `camera`, `missing=lidar`.
    pub fn text(&self) -> String {
        match &self.value {
            Some(v) => format!("{}={}", self.name.name, v.name),
            None => self.name.name.clone(),
        }
    }
}

/// One adaptation rule with its span.
#[derive(Clone, Debug, PartialEq)]
pub struct AdaptRule {
    pub kind: AdaptKind,
    pub span: Span,
}

/// The kinds of adaptation rule.
#[derive(Clone, Debug, PartialEq)]
pub enum AdaptKind {
    /// `tune <selector>`.
    Tune { selector: Selector },
    /// `lora <options> on <selector>`.
    Lora { options: Vec<RuleOption>, selector: Selector },
    /// `adapter <options> in <scopes> before <target>`.
    Adapter { options: Vec<RuleOption>, scopes: Vec<Pattern>, before: Pattern },
    /// `prune <options> [in <selector>]`; no selector: every shared layer.
    Prune { options: Vec<RuleOption>, selector: Option<Selector> },
}

impl AdaptKind {
    pub fn keyword(&self) -> &'static str {
        match self {
            AdaptKind::Tune { .. } => "tune",
            AdaptKind::Lora { .. } => "lora",
            AdaptKind::Adapter { .. } => "adapter",
            AdaptKind::Prune { .. } => "prune",
        }
    }
}

/// `name=value` or a bare flag.
#[derive(Clone, Debug, PartialEq)]
pub struct RuleOption {
    pub name: Ident,
    pub value: Option<OptionValue>,
    pub span: Span,
}

/// The value of a rule option.
#[derive(Clone, Debug, PartialEq)]
pub enum OptionValue {
    Number(Number),
    Str(String, Span),
    Word(Ident),
}

/// Comma-separated selector items.
#[derive(Clone, Debug, PartialEq)]
pub struct Selector {
    pub items: Vec<SelItem>,
    pub span: Span,
}

/// `kinds in scopes`, or a single pattern (which may name an op kind).
#[derive(Clone, Debug, PartialEq)]
pub enum SelItem {
    KindsIn { kinds: Vec<Ident>, scopes: Vec<Pattern>, span: Span },
    Pattern(Pattern),
}

impl SelItem {
    pub fn span(&self) -> Span {
        match self {
            SelItem::KindsIn { span, .. } => *span,
            SelItem::Pattern(p) => p.span,
        }
    }
}

/// A dotted path pattern.
#[derive(Clone, Debug, PartialEq)]
pub struct Pattern {
    pub segments: Vec<PatternSeg>,
    /// The pattern as written.
    pub text: String,
    pub span: Span,
}

impl Pattern {
    /// A pattern that is one plain identifier (no wildcards, no dots): it may name an op
    /// kind or a block.
    pub fn as_single_word(&self) -> Option<&str> {
        match self.segments.as_slice() {
            [PatternSeg::Word(w)] if !w.contains('*') && !w.contains('{') => Some(w),
            _ => None,
        }
    }
}

/// One segment of a path pattern.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PatternSeg {
    /// `**`: any number of segments (including none).
    AnyDepth,
    /// A segment glob: literal text, `*` wildcards and `{a,b}` alternatives.
    Word(String),
}

// -------------------------------------------------------------------------------------
// Variants section
// -------------------------------------------------------------------------------------

/// `variants { declarations }`.
#[derive(Clone, Debug, PartialEq)]
pub struct VariantSection {
    pub decls: Vec<VariantDecl>,
    pub span: Span,
}

/// A number literal of a section, kept with its text so it prints as written.
#[derive(Clone, Debug, PartialEq)]
pub struct Number {
    pub value: f64,
    pub text: String,
    pub span: Span,
}

/// One declaration of the variants section.
#[derive(Clone, Debug, PartialEq)]
pub enum VariantDecl {
    /// `axis name on modality: levels [clear c]`.
    Axis { name: Ident, modality: Ident, levels: Vec<Number>, clear: Option<Number>, span: Span },
    /// `missing modality: policy`.
    Missing { modality: Ident, policy: Ident, span: Span },
    /// `select axis by source [mapping]`.
    Select { axis: Ident, source: SelectSource, mapping: SelectMap, span: Span },
    /// `meld m1 = l1, m2 = l2`.
    Meld { weights: Vec<(Ident, Number)>, span: Span },
}

impl VariantDecl {
    pub fn span(&self) -> Span {
        match self {
            VariantDecl::Axis { span, .. }
            | VariantDecl::Missing { span, .. }
            | VariantDecl::Select { span, .. }
            | VariantDecl::Meld { span, .. } => *span,
        }
    }
}

/// Where a selector's measured value comes from.
#[derive(Clone, Debug, PartialEq)]
pub enum SelectSource {
    /// `meta("key")`.
    Meta { key: String, span: Span },
    /// `statistic(input)`.
    Stat { stat: Ident, input: Ident },
}

/// How a measured value maps to a level.
#[derive(Clone, Debug, PartialEq)]
pub enum SelectMap {
    /// The nearest level (the default).
    Nearest,
    /// The first arm whose threshold the value is below.
    Thresholds(Vec<ThresholdArm>),
}

/// `< t -> level`, `<= t -> level` or `else -> level`.
#[derive(Clone, Debug, PartialEq)]
pub struct ThresholdArm {
    /// `None` for `else`; `Some((inclusive, t))` for `<= t` / `< t`.
    pub bound: Option<(bool, Number)>,
    pub level: LevelRef,
    pub span: Span,
}

/// A level of an axis, or the clear condition.
#[derive(Clone, Debug, PartialEq)]
pub enum LevelRef {
    Clear(Span),
    Level(Number),
}
