//! What `readi inspect -v` lists for a kernel that carries more than its layer: a fused
//! LoRA branch (`lora(rank=4)`, conv and linear), a fused residual adapter
//! (`adapter(mid=8, act=relu)`) and a conv merged on switch (`switch`, with the LoRA it
//! merges: `switch(lora_rank=4)`). Snapshots of the schedule listing (`cargo insta
//! review` to accept changes).

mod common;

use readi_compiler::backend::{self, CompileOptions, LoraMode};
use readi_compiler::passes::choose_strategy::{Conv2dShape, ConvAlgo, Timing};
use readi_runtime::plan::Plan;

/// A LoRA conv, a conv with an adapter behind its (folded) BatchNorm, a LoRA linear.
const SPEC: &str = "block B(x: tensor) {
  conv = conv2d(x, 16, kernel=3, padding=1, bias=false)
  bn = batchnorm(conv)
  return relu(bn)
}
model m {
  input x: f32[N, 16, 8, 8] @camera
  a = conv2d(x, 16, kernel=3, padding=1)
  b = B(relu(a))
  fc = linear(flatten(global_avgpool(b), start=1), 4)
  output y = fc
}
adapt {
  lora rank=4 alpha=8 on a, fc
  adapter squeeze=2 act=relu in B before bn
}
variants {
  axis fog on camera: 0.03, 0.06 clear 0
}
";

fn plan(opts: &CompileOptions) -> Plan {
    let (sources, out) = common::compile_text("inspect.readi", SPEC, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let weights = backend::seeded_weights(&m.graph, 3);
    let keys = vec!["fog=0.03".to_string(), "fog=0.06".to_string()];
    let variants = backend::seeded_variants(&m, &keys, 4);
    let (plan, _) = backend::compile_variants(&m, &weights, "seeded", &variants, opts)
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    plan
}

/// With `--lora branch`: the LoRA branches of `a` and `fc` and the adapter of `b.conv` in
/// their layers' kernels.
#[test]
fn inspect_lists_fused_lora_branches_and_adapters() {
    let p = plan(&CompileOptions { lora: LoraMode::Branch, ..Default::default() });
    let listing = readi::inspect::schedule(&p.manifest, true);
    let line = |path: &str| listing.lines().find(|l| l.contains(path)).unwrap_or_else(|| panic!("{listing}"));
    assert!(line("  a (+lora").contains("conv2d[im2col lora(rank=4) shift relu]"), "{listing}");
    assert!(line("  fc (+lora)").contains("linear[lora(rank=4) shift]"), "{listing}");
    assert!(line("  b.conv (+b.bn, adapter").contains("scale shift adapter(mid=8, act=relu) relu]"), "{listing}");
    insta::assert_snapshot!(listing);
}

/// Milliseconds proportional to multiply-adds (Winograd F(4x4) 4x fewer, F(2x2) 2.25x).
fn macs(s: &Conv2dShape, algo: ConvAlgo) -> f64 {
    let speed = match algo {
        ConvAlgo::Winograd4 => 4.0,
        ConvAlgo::Winograd2 => 2.25,
        _ => 1.0,
    };
    (s.cout * s.k() * s.oh * s.ow) as f64 / speed * 1e-6
}

/// A switch merges and packs the layer's weight: 1e-6 ms per weight element.
fn merge_ms(s: &Conv2dShape, _: ConvAlgo, _: usize) -> f64 {
    (s.cout * s.k()) as f64 * 1e-6
}

/// With `--lora auto`, a memory budget nothing meets and a generous switch budget, `a`
/// is merged on switch: its kernel says so and which LoRA the switch merges.
#[test]
fn inspect_lists_a_conv_merged_on_switch() {
    let opts = CompileOptions {
        lora: LoraMode::Auto,
        memory_budget: Some(0.01),
        switch_budget: Some(1000.0),
        timing: Timing::FixedSwitch(macs, merge_ms),
        ..Default::default()
    };
    let p = plan(&opts);
    let switched = p
        .manifest
        .steps
        .iter()
        .filter(|s| matches!(s.kernel, readi_runtime::plan::Kernel::Conv2d { switch: true, .. }));
    assert_eq!(switched.count(), 1, "{:?}", p.manifest.steps);
    let listing = readi::inspect::schedule(&p.manifest, true);
    let a = listing.lines().find(|l| l.contains("  a (+lora")).unwrap_or_else(|| panic!("{listing}"));
    assert!(a.contains("conv2d[im2col switch(lora_rank=4) shift relu]"), "{listing}");
    insta::assert_snapshot!(listing);
}

/// The header gives each output the element type the model gives it: an `argmax` is
/// i64, a comparison bool.
#[test]
fn inspect_header_shows_output_element_types() {
    let spec = "model m {
  input x: f32[N, 4]
  output y = relu(x)
  output idx = argmax(x, dim=1)
  output big = x > 0.5
}
";
    let (sources, out) = common::compile_text("types.readi", spec, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let weights = backend::seeded_weights(&m.graph, 3);
    let (plan, _) = backend::compile_variants(&m, &weights, "seeded", &[], &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{}", sources.render_all(&d, false)));
    let header = readi::inspect::header(&plan, std::path::Path::new("types.plan"));
    for line in ["  y: f32[N, 4]", "  idx: i64[N]", "  big: bool[N, 4]"] {
        assert!(header.lines().any(|l| l == line), "no line `{line}` in\n{header}");
    }
}
