//! A generator of small well-formed models: chains of conv2d, batchnorm, activations,
//! pooling, linear, add and concat with consistent sizes, and adaptation rules for them.

use super::*;

/// Small choices drawn from one number: `take(n)` is in `0..n`. Proptest shrinks the
/// number towards 0, which makes every choice its first option.
pub(super) struct Draw(u64);

impl Draw {
    pub(super) fn take(&mut self, n: u64) -> u64 {
        let v = self.0 % n;
        self.0 /= n;
        v
    }
    pub(super) fn flag(&mut self) -> bool {
        self.take(2) == 1
    }
    pub(super) fn range(&mut self, lo: i64, hi: i64) -> i64 {
        lo + self.take((hi - lo + 1) as u64) as i64
    }
    pub(super) fn pick<'a, T>(&mut self, xs: &'a [T]) -> &'a T {
        &xs[self.take(xs.len() as u64) as usize]
    }
}

/// The numbers a generated model is made from; see [`generate`].
#[derive(Clone, Debug)]
pub(super) struct GenSpec {
    pub(super) input: u64,
    pub(super) steps: Vec<u64>,
    pub(super) head: u64,
    pub(super) sections: u64,
}

pub(super) fn gen_spec() -> impl Strategy<Value = GenSpec> {
    (any::<u64>(), prop::collection::vec(any::<u64>(), 1..10), any::<u64>(), any::<u64>())
        .prop_map(|(input, steps, head, sections)| GenSpec { input, steps, head, sections })
}

/// A 4-D value `[N, c, h, w]` of the trunk, by the name it has inside the trunk.
#[derive(Clone, Debug)]
pub(super) struct Val {
    pub(super) name: String,
    pub(super) c: i64,
    pub(super) h: i64,
    pub(super) w: i64,
}

impl Val {
    /// The name outside the `trunk` namespace.
    pub(super) fn outside(&self) -> String {
        if self.name.starts_with('l') { format!("trunk.{}", self.name) } else { self.name.clone() }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum LayerKind {
    Conv { fan_in: i64, out: i64, grouped: bool },
    BatchNorm,
    Linear { fan_in: i64, out: i64 },
    Parameter,
}

/// A layer with parameters, for the adaptation rules.
#[derive(Clone, Debug)]
pub(super) struct Layer {
    /// The full path, `trunk.l3.0`.
    pub(super) path: String,
    pub(super) kind: LayerKind,
    /// Channels of its input when that is 4-D (adapter targets in the trunk).
    pub(super) in_c: Option<i64>,
}

/// PyTorch's sliding-window output length, written here again so that the generator does
/// not depend on the compiler's own formula (`pooling_output_shape` with dilation; convs
/// use it without ceil mode).
pub(super) fn window(len: i64, k: i64, s: i64, p: i64, d: i64, ceil: bool) -> Option<i64> {
    let num = len + 2 * p - d * (k - 1) - 1 + if ceil { s - 1 } else { 0 };
    if num < 0 {
        return None;
    }
    let mut out = num / s + 1;
    if ceil && (out - 1) * s >= len + p {
        out -= 1;
    }
    (1..=16).contains(&out).then_some(out)
}

pub(super) fn pair(v: [i64; 2]) -> String {
    if v[0] == v[1] { v[0].to_string() } else { format!("[{}, {}]", v[0], v[1]) }
}

pub(super) fn divisors(n: i64) -> Vec<i64> {
    (1..=n).filter(|d| n % d == 0).collect()
}

pub(super) fn gcd(a: i64, b: i64) -> i64 {
    if b == 0 { a } else { gcd(b, a % b) }
}

pub(super) struct Gen {
    pub(super) trunk: Vec<String>,
    pub(super) vals: Vec<Val>,
    pub(super) layers: Vec<Layer>,
    pub(super) uses_unit: bool,
}

impl Gen {
    pub(super) fn cur(&self) -> Val {
        self.vals.last().cloned().expect("the input")
    }

    pub(super) fn push(&mut self, name: String, rhs: String, c: i64, h: i64, w: i64) {
        self.trunk.push(format!("    {name} = {rhs}"));
        self.vals.push(Val { name, c, h, w });
    }

    pub(super) fn layer(&mut self, path: String, kind: LayerKind, in_c: Option<i64>) {
        self.layers.push(Layer { path, kind, in_c });
    }

    /// An earlier value with this shape, other than `cur`.
    pub(super) fn same_shape(&self, cur: &Val, d: &mut Draw, fits: impl Fn(&Val) -> bool) -> Option<Val> {
        let found: Vec<&Val> = self.vals.iter().filter(|v| v.name != cur.name && fits(v)).collect();
        (!found.is_empty()).then(|| (*d.pick(&found)).clone())
    }

    pub(super) fn step(&mut self, i: usize, r: u64) {
        let mut d = Draw(r);
        let x = self.cur();
        let name = format!("l{i}");
        let (c, h, w) = (x.c, x.h, x.w);
        let xn = &x.name;
        match d.take(20) {
            0 | 13 => self.conv(&name, &x, &mut d),
            1 => {
                let eps = *d.pick(&["", ", eps=1e-3", ", eps=1e-5, momentum=0.01"]);
                self.layer(format!("trunk.{name}"), LayerKind::BatchNorm, Some(c));
                self.push(name, format!("batchnorm({xn}{eps})"), c, h, w);
            }
            2 => {
                let act = *d.pick(&["relu", "sigmoid", "tanh", "silu", "gelu"]);
                let rhs = match act {
                    "gelu" if d.flag() => format!("gelu({xn}, approximate=\"tanh\")"),
                    a => format!("{a}({xn})"),
                };
                self.push(name, rhs, c, h, w);
            }
            3 => self.pool(&name, &x, &mut d),
            4 => {
                let op = *d.pick(&["+", "-", "*"]);
                let rhs = match self.same_shape(&x, &mut d, |v| (v.c, v.h, v.w) == (c, h, w)) {
                    Some(o) => format!("{xn} {op} {}", o.name),
                    None => format!("{} {op} {xn}", *d.pick(&["relu(XX)", "sigmoid(XX)", "XX"])).replace("XX", xn),
                };
                self.push(name, rhs, c, h, w);
            }
            5 => match self.same_shape(&x, &mut d, |v| (v.h, v.w) == (h, w) && v.c + c <= 16) {
                Some(o) => {
                    let (a, b) = if d.flag() { (xn.clone(), o.name) } else { (o.name, xn.clone()) };
                    self.push(name, format!("concat([{a}, {b}], axis=1)"), c + o.c, h, w);
                }
                None if 2 * c <= 16 => self.push(name, format!("concat([{xn}, {xn}], axis=1)"), 2 * c, h, w),
                None => self.push(name, format!("relu({xn})"), c, h, w),
            },
            6 => {
                let mode = if d.flag() {
                    let align = if d.flag() { ", align_corners=true" } else { "" };
                    format!(", mode=\"bilinear\"{align}")
                } else {
                    String::new()
                };
                let (oh, ow, how) = match d.take(3) {
                    0 if 2 * h <= 16 && 2 * w <= 16 => (2 * h, 2 * w, "scale=2".to_string()),
                    1 if h >= 2 && w >= 2 => (h / 2, w / 2, "scale=0.5".to_string()),
                    _ => {
                        let (oh, ow) = (d.range(1, 16), d.range(1, 16));
                        (oh, ow, format!("size=[{oh}, {ow}]"))
                    }
                };
                self.push(name, format!("upsample({xn}, {how}{mode})"), c, oh, ow);
            }
            7 => match d.take(5) {
                0 => self.push(name, format!("permute({xn}, [0, 1, 3, 2])"), c, w, h),
                1 => self.push(name, format!("transpose({xn}, 3, 2)"), c, w, h),
                2 => self.push(name, format!("reshape({xn}, [dim({xn}, 0), {c}, {w}, {h}])"), c, w, h),
                3 if h <= 16 => self.push(name, format!("permute({xn}, [0, 2, 1, 3])"), h, c, w),
                _ => self.push(name, format!("reshape(flatten({xn}, start=1), [-1, {c}, {h}, {w}])"), c, h, w),
            },
            8 => {
                let rhs = match d.take(5) {
                    0 => format!("{xn} * 0.5 + 0.25"),
                    1 => format!("1 - {xn}"),
                    2 => format!("-{xn}"),
                    3 => format!("{xn} / 2.0"),
                    _ => format!("{xn} * {xn}"),
                };
                self.push(name, rhs, c, h, w);
            }
            9 => {
                // Not a smaller eps than the default: see `differs`.
                let args = *d.pick(&["", ", eps=1e-3", ", affine=false"]);
                self.push(name, format!("layernorm({xn}{args})"), c, h, w);
            }
            10 => {
                let axis = *d.pick(&["", ", axis=1", ", axis=2", ", axis=-1"]);
                self.push(name, format!("softmax({xn}{axis})"), c, h, w);
            }
            11 => {
                let rhs = match d.take(3) {
                    0 => format!("{xn} * sigmoid(mean({xn}, axes=[2, 3], keepdim=true))"),
                    1 => format!("{xn} + global_avgpool({xn})"),
                    _ => format!("upsample(global_avgpool({xn}), size=[{h}, {w}])"),
                };
                self.push(name, rhs, c, h, w);
            }
            15 => {
                // A learned tensor used as a value (stored in the plan, not an input).
                let (pc, ph, pw) = *d.pick(&[(c, h, w), (1, h, w), (c, 1, 1), (1, 1, 1)]);
                let p = format!("p{i}");
                self.trunk.push(format!("    {p} = parameter([1, {pc}, {ph}, {pw}])"));
                self.layer(format!("trunk.{p}"), LayerKind::Parameter, None);
                let op = *d.pick(&["+", "*"]);
                self.push(name, format!("{xn} {op} {p}"), c, h, w);
            }
            16 => {
                self.push(name, format!("matmul({xn}, transpose({xn}, 2, 3))"), c, h, h);
            }
            17 => match self.same_shape(&x, &mut d, |v| v.c == c && v.h == h && v.w + w <= 16) {
                Some(o) => self.push(name, format!("concat([{xn}, {}], axis=3)", o.name), c, h, w + o.w),
                None if 2 * h <= 16 => self.push(name, format!("concat([{xn}, {xn}], axis=-2)"), c, 2 * h, w),
                None => self.push(name, format!("{xn} / (sigmoid({xn}) + 1)"), c, h, w),
            },
            18 => {
                let k = d.range(1, 16);
                let bias = if d.flag() { "" } else { ", bias=false" };
                self.layer(format!("trunk.{name}"), LayerKind::Linear { fan_in: w, out: k }, Some(c));
                self.push(name, format!("linear({xn}, {k}{bias})"), c, h, k);
            }
            12 => {
                self.uses_unit = true;
                self.layer(
                    format!("trunk.{name}.conv"),
                    LayerKind::Conv { fan_in: c * 9, out: c, grouped: false },
                    Some(c),
                );
                self.layer(format!("trunk.{name}.bn"), LayerKind::BatchNorm, Some(c));
                self.push(name, format!("Unit({xn}, {c})"), c, h, w);
            }
            _ => {
                let out = d.range(1, 16);
                let bias = if d.flag() { "" } else { ", bias=false" };
                self.layer(format!("trunk.{name}.0"), LayerKind::Conv { fan_in: c * 9, out, grouped: false }, Some(c));
                self.layer(format!("trunk.{name}.1"), LayerKind::BatchNorm, Some(out));
                let act = *d.pick(&["relu", "silu", "sigmoid"]);
                self.trunk.push(format!(
                    "    {name} = seq({xn}) {{\n      conv2d({out}, kernel=3, padding=1{bias})\n      batchnorm\n      {act}\n    }}"
                ));
                self.vals.push(Val { name, c: out, h, w });
            }
        }
    }

    pub(super) fn conv(&mut self, name: &str, x: &Val, d: &mut Draw) {
        let out = d.range(1, 16);
        let mut k = [d.range(1, 3), 0];
        k[1] = if d.flag() { k[0] } else { d.range(1, 3) };
        let mut s = [d.range(1, 2), 0];
        s[1] = if d.flag() { s[0] } else { d.range(1, 2) };
        let mut p = [d.range(0, 2), 0];
        p[1] = if d.flag() { p[0] } else { d.range(0, 2) };
        let mut dil = [if d.take(4) == 0 { 2 } else { 1 }, 1];
        dil[1] = dil[0];
        let mut o = [0; 2];
        for (a, len) in [x.h, x.w].into_iter().enumerate() {
            o[a] = match window(len, k[a], s[a], p[a], dil[a], false) {
                Some(v) => v,
                None => {
                    (k[a], s[a], p[a], dil[a]) = (1, 1, 0, 1);
                    len
                }
            };
        }
        let groups = *d.pick(&divisors(gcd(x.c, out)));
        let mut args = format!("{}, {out}, kernel={}", x.name, pair(k));
        if s != [1, 1] || d.flag() {
            args += &format!(", stride={}", pair(s));
        }
        if p != [0, 0] {
            args += &format!(", padding={}", pair(p));
        }
        if dil != [1, 1] {
            args += &format!(", dilation={}", pair(dil));
        }
        if groups > 1 {
            args += &format!(", groups={groups}");
        }
        if d.flag() {
            args += ", bias=false";
        }
        let kind = LayerKind::Conv { fan_in: x.c / groups * k[0] * k[1], out, grouped: groups > 1 };
        self.layer(format!("trunk.{name}"), kind, Some(x.c));
        self.push(name.to_string(), format!("conv2d({args})"), out, o[0], o[1]);
    }

    pub(super) fn pool(&mut self, name: &str, x: &Val, d: &mut Draw) {
        let avg = d.flag();
        let k = [d.range(1, 3), d.range(1, 3)];
        let s = if d.flag() { None } else { Some([d.range(1, 3), d.range(1, 3)]) };
        let p = [d.range(0, k[0] / 2), d.range(0, k[1] / 2)];
        let ceil = d.flag();
        let stride = s.unwrap_or(k);
        let (mut oh, mut ow) =
            (window(x.h, k[0], stride[0], p[0], 1, ceil), window(x.w, k[1], stride[1], p[1], 1, ceil));
        let mut args = format!("{}, kernel={}", x.name, pair(k));
        if oh.is_none() || ow.is_none() {
            args = format!("{}, kernel=1", x.name);
            (oh, ow) = (Some(x.h), Some(x.w));
        } else {
            if let Some(s) = s {
                args += &format!(", stride={}", pair(s));
            }
            if p != [0, 0] {
                args += &format!(", padding={}", pair(p));
            }
            if ceil {
                args += ", ceil_mode=true";
            }
            if avg && d.flag() {
                args += ", count_include_pad=false";
            }
        }
        let op = if avg { "avgpool" } else { "maxpool" };
        self.push(name.to_string(), format!("{op}({args})"), x.c, oh.unwrap_or(1), ow.unwrap_or(1));
    }
}

/// A random model that should check: an input `x` (and maybe a second, `y`, of the same
/// shape), a chain of 4-D layers in namespace `trunk` whose channel counts and window
/// geometry fit (channels and spatial sizes at most 16), a head (nothing, a classifier, or
/// attention over the spatial positions), maybe an `adapt` section with rules that fit
/// the layers, and maybe a `variants` section.
pub(super) fn generate(g: &GenSpec) -> String {
    generate_with(g, false)
}

/// [`generate`], with every value of the trunk also an output (`v_l3 = trunk.l3`) when
/// `all_outputs`.
pub(super) fn generate_with(g: &GenSpec, all_outputs: bool) -> String {
    let mut d = Draw(g.input);
    let (c, h, w) = (d.range(1, 8), d.range(1, 16), d.range(1, 16));
    let x_optional = d.flag();
    let with_y = d.flag();
    let mut model =
        vec![format!("  input x: f32[N, {c}, {h}, {w}] @camera{}", if x_optional { " optional" } else { "" })];
    let mut st = Gen { trunk: vec![], vals: vec![Val { name: "x".into(), c, h, w }], layers: vec![], uses_unit: false };
    if with_y {
        model.push(format!("  input y: f32[N, {c}, {h}, {w}] @lidar optional"));
        st.vals.push(Val { name: "y".into(), c, h, w });
        // Steps that look for a value of `x`'s shape may pick `y`.
        st.vals.swap(0, 1);
    }
    for (i, &r) in g.steps.iter().enumerate() {
        st.step(i, r);
    }
    let last = st.cur();
    model.push("  trunk {".into());
    model.append(&mut st.trunk);
    model.push("  }".into());
    let mut outputs = vec![format!("  output features = {}", last.outside())];

    let mut d = Draw(g.head);
    match d.take(4) {
        1 => {
            let k = d.range(1, 16);
            model.push(format!("  head {{\n    pooled = flatten(global_avgpool({}), start=1)", last.outside()));
            model.push(format!("    fc = linear(pooled, {k})"));
            st.layer("head.fc".into(), LayerKind::Linear { fan_in: last.c, out: k }, None);
            if d.flag() {
                let k2 = d.range(1, 16);
                model.push(format!("    fc2 = linear(relu(fc), {k2}{})", if d.flag() { ", bias=false" } else { "" }));
                st.layer("head.fc2".into(), LayerKind::Linear { fan_in: k, out: k2 }, None);
                outputs.push("  output logits = head.fc2".into());
            } else {
                outputs.push("  output logits = head.fc".into());
            }
            model.push("  }".into());
        }
        2 => {
            let (cc, hd) = (last.c, d.range(1, 8));
            model.push(format!("  head {{\n    tokens = transpose(flatten({}, start=2), 1, 2)", last.outside()));
            model.push("    norm = layernorm(tokens)".into());
            for p in ["q", "k", "v"] {
                model.push(format!("    {p} = linear(norm, {hd})"));
                st.layer(format!("head.{p}"), LayerKind::Linear { fan_in: cc, out: hd }, None);
            }
            let scale = 1.0 / (hd as f64).sqrt();
            model.push(format!("    attn = softmax(matmul(q, transpose(k, 1, 2)) * {scale:.4}, axis=-1)"));
            model.push(format!("    proj = linear(matmul(attn, v), {cc})"));
            st.layer("head.proj".into(), LayerKind::Linear { fan_in: hd, out: cc }, None);
            model.push("    mixed = tokens + proj\n  }".into());
            outputs.push(format!("  output summary = mean(head.mixed, axes={})", d.pick(&["1", "[1, 2]", "-1"])));
        }
        3 => {
            let k = d.range(1, 16);
            model.push(format!("  head {{\n    fc = linear(flatten({}, start=1), {k})\n  }}", last.outside()));
            st.layer("head.fc".into(), LayerKind::Linear { fan_in: last.c * last.h * last.w, out: k }, None);
            outputs.push("  output logits = head.fc".into());
        }
        _ => {}
    }
    if d.take(4) == 0 {
        let v = d.pick(&st.vals).clone();
        outputs.push(format!("  output early = {}", v.outside()));
    }
    if all_outputs {
        outputs.extend(
            st.vals
                .iter()
                .filter(|v| v.name.starts_with('l'))
                .map(|v| format!("  output v_{} = {}", v.name, v.outside())),
        );
    }
    model.append(&mut outputs);

    let mut text = String::new();
    if st.uses_unit {
        text.push_str(
            "block Unit(x: tensor, planes: int) {\n  conv = conv2d(x, planes, kernel=3, padding=1, bias=false)\n  \
             bn = batchnorm(conv)\n  return relu(bn + x)\n}\n",
        );
    }
    text.push_str("model g {\n");
    text.push_str(&model.join("\n"));
    text.push_str("\n}\n");

    let mut d = Draw(g.sections);
    let rules = if d.flag() { adapt_rules(&st.layers, &mut d) } else { vec![] };
    if !rules.is_empty() {
        text.push_str(&format!("adapt {{\n  {}\n}}\n", rules.join("\n  ")));
    }
    if d.flag() {
        let mut decls =
            vec![d.pick(&["axis fog on camera: 0.1, 0.2 clear 0", "axis gamma on camera: 0.5, 2 clear 1"]).to_string()];
        if with_y && d.flag() {
            decls.push("missing lidar: variant".into());
        }
        if x_optional && d.flag() {
            decls.push("missing camera: zero_fill".into());
        }
        text.push_str(&format!("variants {{\n  {}\n}}\n", decls.join("\n  ")));
    }
    text
}

/// Rules that fit the layers: tune some, LoRA on one that is not tuned, an adapter before
/// one whose input is 4-D with a squeeze ratio that divides its channels.
pub(super) fn adapt_rules(layers: &[Layer], d: &mut Draw) -> Vec<String> {
    let mut rules = Vec::new();
    let mut tuned: Vec<&str> = Vec::new();
    if d.flag() {
        if layers.iter().any(|l| l.kind == LayerKind::BatchNorm) && d.flag() {
            rules.push("tune batchnorm".to_string());
            tuned.extend(layers.iter().filter(|l| l.kind == LayerKind::BatchNorm).map(|l| l.path.as_str()));
        } else if !layers.is_empty() {
            let l = d.pick(layers);
            rules.push(format!("tune {}", l.path));
            tuned.push(&l.path);
        }
    }
    let lora: Vec<(&Layer, i64)> = layers
        .iter()
        .filter(|l| !tuned.contains(&l.path.as_str()))
        .filter_map(|l| match l.kind {
            LayerKind::Conv { fan_in, out, grouped: false } | LayerKind::Linear { fan_in, out } => {
                Some((l, fan_in.min(out)))
            }
            _ => None,
        })
        .collect();
    if !lora.is_empty() && d.flag() {
        let (l, max) = *d.pick(&lora);
        let rank = d.range(1, max.min(4));
        let extra = *d.pick(&["", " alpha=4", " alpha=2 rslora"]);
        rules.push(format!("lora rank={rank}{extra} on {}", l.path));
    }
    let adapters: Vec<(&Layer, i64)> = layers.iter().filter_map(|l| Some((l, l.in_c?))).collect();
    if !adapters.is_empty() && d.flag() {
        let (l, c) = *d.pick(&adapters);
        let squeeze = *d.pick(&divisors(c));
        let act = *d.pick(&["relu", "gelu", "sigmoid"]);
        let rel = l.path.strip_prefix("trunk.").unwrap_or(&l.path);
        rules.push(format!("adapter squeeze={squeeze} act={act} in trunk before {rel}"));
    }
    rules
}
