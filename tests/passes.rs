//! One snapshot per pass case: `tests/cases/passes/<pass>/*.readi`, each run up to the
//! pass before and up to the pass itself, with the IR (or, from `lower` on, the schedule)
//! after the pass and the diff from before it. The cases document each rewrite: every
//! rewriting pass has a case where it applies and one where its guard stops it.
//!
//! A case starts with `#` header lines:
//!
//! * `# expect: change` or `# expect: no change` (required): whether the pass changes
//!   what is printed. Checked, so a guard that stops working fails the case.
//! * `# variants: fog=0.03, gamma=4`: seeded variants with these keys;
//! * `# lora: branch` (default merge); `# meld: fog=0.06+gamma=0.5`;
//! * `# seed: 3`: the seed of the weights (default 1; the variants get seed + 1);
//! * `# zero: b.bn.weight, ...`: base tensors set to zero (to trip a guard).
//!
//! Other `#` lines describe the case. Add a case by adding a file and running
//! `cargo insta review` (or `INSTA_UPDATE=always cargo test --test passes`).

mod common;

use readi_compiler::backend::{self, CompileOptions, LoraMode};
use readi_compiler::passes::{self, BackendInputs, PIPELINE, Pass};
use readi_compiler::print::to_text;
use readi_compiler::{Module, Options};
use readi_grammar::diag::SourceMap;

/// A case's header.
#[derive(Default)]
struct Header {
    expect_change: Option<bool>,
    variants: Vec<String>,
    lora: LoraMode,
    melds: Vec<String>,
    seed: u64,
    zero: Vec<String>,
}

fn header(text: &str, rel: &str) -> Header {
    let mut h = Header { seed: 1, ..Header::default() };
    let list = |v: &str| v.split(',').map(|s| s.trim().to_string()).filter(|s| !s.is_empty()).collect::<Vec<_>>();
    for line in text.lines().take_while(|l| l.starts_with('#')) {
        let Some((key, value)) = line.trim_start_matches('#').split_once(':') else { continue };
        let value = value.trim();
        match key.trim() {
            "expect" => {
                h.expect_change = Some(match value {
                    "change" => true,
                    "no change" => false,
                    other => panic!("{rel}: `# expect: {other}`; write `change` or `no change`"),
                })
            }
            "variants" => h.variants = list(value),
            "lora" => h.lora = if value == "branch" { LoraMode::Branch } else { LoraMode::Merge },
            "meld" => h.melds = list(value),
            "seed" => h.seed = value.parse().unwrap_or_else(|_| panic!("{rel}: bad seed `{value}`")),
            "zero" => h.zero = list(value),
            _ => {}
        }
    }
    h
}

/// The pass before `pass` in the pipeline.
fn previous(pass: Pass) -> Pass {
    let i = PIPELINE.iter().position(|p| p.0 == pass).expect("a pass of the pipeline");
    PIPELINE[i - 1].0
}

/// The module (or its schedule) as text after `stop`, for a case, and the rules `stop`
/// applied (`fold_into_conv x2`), if it is a back-end pass.
fn after(rel: &str, text: &str, h: &Header, stop: Pass) -> (String, Vec<String>) {
    let mut sources = SourceMap::new();
    let file = sources.add(rel, text);
    let front_stop = if stop.is_backend() { None } else { Some(stop) };
    let out = passes::run(file, text, &Options { stop_after: front_stop, ..Options::default() });
    assert!(!out.diagnostics.has_errors(), "{rel}: {}", sources.render_all(&out.diagnostics, false));
    let mut module: Module = out.module.unwrap_or_else(|| panic!("{rel}: no module"));
    if !stop.is_backend() {
        return (to_text(&module), Vec::new());
    }
    let mut weights = backend::seeded_weights(&module.graph, h.seed);
    for name in &h.zero {
        let (_, data) = weights.tensors.get_mut(name).unwrap_or_else(|| panic!("{rel}: no tensor `{name}` to zero"));
        data.iter_mut().for_each(|v| *v = 0.0);
    }
    let sources_v = backend::seeded_variants(&module, &h.variants, h.seed + 1);
    let opts = CompileOptions { lora: h.lora, melds: h.melds.clone(), ..CompileOptions::default() };
    let inputs = BackendInputs { base: &weights, base_name: "seeded", variants: &sources_v, opts: &opts };
    let run = passes::run_backend(&mut module, &inputs, Some(stop))
        .unwrap_or_else(|d| panic!("{rel}: {}", sources.render_all(&d, false)));
    let rules = run.applied.iter().filter(|a| a.pass == stop).map(|a| format!("{} x{}", a.rule, a.count)).collect();
    let text = match &module.lowered {
        Some(l) => {
            let m = &l.manifest;
            readi::inspect::schedule(m, true) + &readi::inspect::buffers(m) + &readi::inspect::variant_tables(m)
        }
        None => to_text(&module),
    };
    (text, rules)
}

#[test]
fn pass_cases() {
    let mut count = 0;
    insta::glob!("cases/passes/*/*.readi", |path| {
        let rel = common::rel_path(path);
        let dir = path.parent().and_then(|p| p.file_name()).and_then(|d| d.to_str()).expect("a pass directory");
        let pass = Pass::from_name(dir).unwrap_or_else(|| panic!("{rel}: `{dir}` is not a pass (see `readi passes`)"));
        let text = std::fs::read_to_string(path).expect("read the case");
        let h = header(&text, &rel);
        let expect = h.expect_change.unwrap_or_else(|| panic!("{rel}: no `# expect:` line"));
        let (before, _) = after(&rel, &text, &h, previous(pass));
        let (now, rules) = after(&rel, &text, &h, pass);
        assert_eq!(
            before != now,
            expect,
            "{rel}: expected {}, got the opposite",
            if expect { "a change" } else { "no change" }
        );
        let diff = similar::TextDiff::from_lines(&before, &now).unified_diff().context_radius(1).to_string();
        let comment: String = text.lines().take_while(|l| l.starts_with('#')).map(|l| format!("{l}\n")).collect();
        let shown = match (pass, diff.is_empty()) {
            // Lowering turns the IR into a schedule: the diff would be all of both.
            (Pass::Lower, _) => "(the IR becomes the schedule above)\n".to_string(),
            (_, true) => "(no change)\n".to_string(),
            (_, false) => diff,
        };
        let rules = if rules.is_empty() { String::new() } else { format!("rules applied: {}\n", rules.join(", ")) };
        insta::assert_snapshot!(format!("{comment}\n--- after {dir}\n{rules}{now}\n--- diff from before\n{shown}"));
        count += 1;
    });
    assert!(count >= 25, "expected at least 25 pass cases, found {count}");
}

#[test]
fn every_rewriting_pass_has_cases_both_ways() {
    // A pass's directory must hold a case where it applies and, for a rewrite with a
    // guard, one where it does not.
    let root = common::root().join("tests/cases/passes");
    let always = ["bind_weights", "lower", "plan_buffers"];
    for &(pass, name, _) in PIPELINE.iter().filter(|p| p.0 > Pass::Elaborate) {
        if matches!(pass, Pass::ResolveAdapt | Pass::CheckVariants | Pass::ChooseStrategy) {
            continue; // side tables with their own language cases (choose_strategy: tests/strategy.rs)
        }
        let dir = root.join(name);
        let mut kinds = (false, false);
        for entry in
            std::fs::read_dir(&dir).unwrap_or_else(|_| panic!("no cases for pass `{name}` in {}", dir.display()))
        {
            let text = std::fs::read_to_string(entry.expect("entry").path()).expect("read");
            let h = header(&text, name);
            match h.expect_change {
                Some(true) => kinds.0 = true,
                Some(false) => kinds.1 = true,
                None => {}
            }
        }
        assert!(kinds.0, "pass `{name}` has no case where it applies");
        assert!(kinds.1 || always.contains(&name), "pass `{name}` has no case where its guard stops it");
    }
}
