//! File-driven snapshot tests (`cargo insta review` to inspect and accept changes):
//!
//! * every model in models/: the IR text after the whole pipeline, with the verifier
//!   run after every pass, and before `inject_adapt` (so the pair shows what the LoRA
//!   branches and adapters add);
//! * every case in tests/cases/ok/: the IR text, with no diagnostics allowed;
//! * every case in tests/cases/errors/: the rendered diagnostics, which must include at
//!   least one error with `file:line:col`, the source line and a caret;
//! * every case in tests/cases/warnings/: the rendered warnings of a file that checks.

mod common;

use common::{compile, rel_path};
use readi_compiler::passes::{PIPELINE, Pass};
use readi_compiler::print::to_text;
use readi_compiler::verify::verify;

/// Runs the pipeline stopping after each pass and verifies the module at every stop.
fn verify_every_pass(rel: &str) {
    for &(pass, name, _) in PIPELINE {
        if pass == Pass::Parse {
            continue;
        }
        let (sources, out) = compile(rel, &[], Some(pass));
        assert!(!out.diagnostics.has_errors(), "{rel}: {}", sources.render_all(&out.diagnostics, false));
        let module = out.module.unwrap_or_else(|| panic!("{rel}: no module after {name}"));
        if let Err(problems) = verify(&module) {
            panic!("{rel}: verifier after `{name}`: {problems:#?}");
        }
    }
}

/// Checks a file cleanly, verifying after every pass, and snapshots its IR text.
fn ir_snapshot(name: &str, path: &std::path::Path) {
    let rel = rel_path(path);
    verify_every_pass(&rel);
    let (sources, out) = compile(&rel, &[], None);
    assert!(out.diagnostics.is_empty(), "{rel}: {}", sources.render_all(&out.diagnostics, false));
    insta::assert_snapshot!(name, to_text(&out.module.expect("module")));
}

#[test]
fn model_ir() {
    insta::glob!("../models", "*.readi", |path| {
        ir_snapshot("model_ir", path);
        let rel = rel_path(path);
        let (sources, out) = compile(&rel, &[], Some(Pass::ResolveAdapt));
        assert!(out.diagnostics.is_empty(), "{rel}: {}", sources.render_all(&out.diagnostics, false));
        insta::assert_snapshot!("model_ir_before_inject_adapt", to_text(&out.module.expect("module")));
    });
}

#[test]
fn language_cases() {
    insta::glob!("cases/ok/*.readi", |path| ir_snapshot("language_cases", path));
}

#[test]
fn error_messages() {
    let mut count = 0;
    insta::glob!("cases/errors/*.readi", |path| {
        count += 1;
        let rel = rel_path(path);
        let (sources, out) = compile(&rel, &[], None);
        assert!(out.diagnostics.has_errors(), "{rel} should fail to check");
        let rendered = sources.render_all(&out.diagnostics, false);
        // Every error points at file:line:col and underlines the place.
        for d in out.diagnostics.iter().filter(|d| d.is_error()) {
            let span = d.primary_span().expect("every error has a primary label");
            let (line, col) = sources.line_col(span);
            let place = format!("{rel}:{line}:{col}");
            assert!(rendered.contains(&place), "{rel}: `{place}` missing from\n{rendered}");
        }
        assert!(rendered.contains('^'), "{rel}: no caret in\n{rendered}");
        insta::assert_snapshot!(rendered);
    });
    assert!(count >= 20, "expected at least 20 error cases, found {count}");
}

#[test]
fn warning_messages() {
    insta::glob!("cases/warnings/*.readi", |path| {
        let rel = rel_path(path);
        let (sources, out) = compile(&rel, &[], None);
        let rendered = sources.render_all(&out.diagnostics, false);
        assert!(!out.diagnostics.has_errors(), "{rel} should check:\n{rendered}");
        assert!(out.diagnostics.warning_count() > 0, "{rel} should warn");
        insta::assert_snapshot!(rendered);
    });
}
