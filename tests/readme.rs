//! The README's language tour is a complete spec; it must keep checking cleanly.

mod common;

#[test]
fn readme_tour_checks() {
    let readme = std::fs::read_to_string(common::root().join("README.md")).expect("README.md");
    let start = readme.find("```readi\n").expect("a ```readi block") + "```readi\n".len();
    let len = readme[start..].find("```").expect("closed block");
    let (sources, out) = common::compile_text("README.md", &readme[start..start + len], &[], None);
    assert!(out.diagnostics.is_empty(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    assert!(m.adapt.is_some() && m.variants.is_some());
}
