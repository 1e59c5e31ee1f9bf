//! `use "other.readi"`: a file's items together with those of the files it uses.
//!
//! A used file brings its blocks. Its model, its `adapt` sections and its `variants`
//! section come too unless the using file has its own of that kind: a deployment file can
//! then hold only the adaptation and the conditions for a model written elsewhere
//! (`use "resnet50.readi"` and an `adapt` section), replacing the model file's own, and a
//! model can be assembled from the blocks of part files that each keep a model of their
//! own for testing (`models/bevfusion.readi` uses `models/bevfusion/*.readi`). Paths are
//! relative to the file that writes them; reading them is the caller's (a [`Load`]), so
//! the parser itself never touches the file system.
//!
//! Each file is included once: a file reached twice (two files use a third) or a cycle
//! adds nothing the second time. Uses nest at most [`MAX_USE_DEPTH`] deep. Diagnostics
//! of a used file point into that file (its own [`FileId`]).

use crate::ast::{Item, SourceFile};
use crate::diag::{Code, Diagnostic, Diagnostics, FileId};
use crate::parser::{Parsed, parse};

/// How deep `use` may nest.
pub const MAX_USE_DEPTH: usize = 16;

/// Reads the file `path` names, as written in file `from`: its id (the same id for the
/// same file every time) and its text, or why it cannot be read.
pub type Load<'a> = dyn FnMut(FileId, &str) -> Result<(FileId, String), String> + 'a;

/// Parses `src` (file `file`) and every file it uses, through `load`.
pub fn parse_with_uses(file: FileId, src: &str, load: &mut Load<'_>) -> Parsed {
    let mut seen = vec![file];
    let mut diagnostics = Diagnostics::default();
    let items = expand(file, parse(file, src), load, &mut seen, &mut diagnostics, 0);
    Parsed { file: SourceFile { items }, diagnostics }
}

fn expand(
    file: FileId,
    parsed: Parsed,
    load: &mut Load<'_>,
    seen: &mut Vec<FileId>,
    diags: &mut Diagnostics,
    depth: usize,
) -> Vec<Item> {
    diags.extend(parsed.diagnostics);
    let own = parsed.file.items;
    let has_model = own.iter().any(|i| matches!(i, Item::Model(_)));
    let has_adapt = own.iter().any(|i| matches!(i, Item::Adapt(_)));
    let has_variants = own.iter().any(|i| matches!(i, Item::Variants(_)));
    let mut items = Vec::with_capacity(own.len());
    for item in own {
        let Item::Use(u) = &item else {
            items.push(item);
            continue;
        };
        if depth >= MAX_USE_DEPTH {
            diags.push(
                Diagnostic::error(Code::Limit, format!("`use` nests more than {MAX_USE_DEPTH} files deep"))
                    .with_primary(u.span, "one use too many"),
            );
            continue;
        }
        let (used, text) = match load(file, &u.path) {
            Ok(loaded) => loaded,
            Err(why) => {
                diags.push(
                    Diagnostic::error(Code::UseFile, format!("cannot use `{}`: {why}", u.path))
                        .with_primary(u.span, "used here"),
                );
                continue;
            }
        };
        if seen.contains(&used) {
            continue;
        }
        seen.push(used);
        let parsed = parse(used, &text);
        for i in expand(used, parsed, load, seen, diags, depth + 1) {
            match i {
                Item::Model(_) if has_model => {}
                Item::Adapt(_) if has_adapt => {}
                Item::Variants(_) if has_variants => {}
                i => items.push(i),
            }
        }
    }
    items
}

/// A [`Load`] for sources that are not files: every `use` is an error.
pub fn no_files(_: FileId, _: &str) -> Result<(FileId, String), String> {
    Err("this source is not read from a file, so it cannot name other files".into())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diag::SourceMap;

    /// An in-memory file system: name -> text; ids are assigned once per name.
    struct Files {
        map: SourceMap,
        files: Vec<(&'static str, &'static str)>,
        ids: Vec<(&'static str, FileId)>,
    }

    impl Files {
        fn load(&mut self, _: FileId, path: &str) -> Result<(FileId, String), String> {
            let (name, text) = *self.files.iter().find(|(n, _)| *n == path).ok_or("no such file")?;
            if let Some((_, id)) = self.ids.iter().find(|(n, _)| *n == name) {
                return Ok((*id, text.to_string()));
            }
            let id = self.map.add(name, text);
            self.ids.push((name, id));
            Ok((id, text.to_string()))
        }
    }

    fn parse_root(files: Vec<(&'static str, &'static str)>, root: &'static str) -> (Parsed, SourceMap) {
        let mut fs = Files { map: SourceMap::new(), files, ids: Vec::new() };
        let (id, text) = fs.load(FileId(0), root).expect("root");
        let parsed = parse_with_uses(id, &text, &mut |from, p| fs.load(from, p));
        (parsed, fs.map)
    }

    const MODEL: &str = "block B(x) { return relu(x) }\nmodel m { input x: f32[N, 4]\n output y = B(x) }\nadapt { tune fc }\nvariants { axis fog on camera: 0.01 }\n";

    #[test]
    fn a_used_file_brings_its_items_and_own_sections_replace_its_sections() {
        let deploy = "use \"m.readi\"\nadapt { tune batchnorm }\n";
        let (p, _) = parse_root(vec![("m.readi", MODEL), ("d.readi", deploy)], "d.readi");
        assert!(p.diagnostics.is_empty(), "{:?}", p.diagnostics);
        assert_eq!(p.file.blocks().count(), 1);
        assert_eq!(p.file.models().count(), 1);
        // The deployment's adapt section replaces the model file's; its variants come along.
        let adapts: Vec<_> = p.file.adapt_sections().collect();
        assert_eq!(adapts.len(), 1);
        let rules = format!("{:?}", adapts[0].rules);
        assert!(rules.contains("batchnorm") && !rules.contains("\"fc\""), "{rules}");
        assert_eq!(p.file.variant_sections().count(), 1);
        assert_eq!(p.file.uses().count(), 0, "uses are resolved away");
    }

    #[test]
    fn a_model_assembled_from_part_files_keeps_only_its_own_model() {
        let a = "block A(x) { return relu(x) }\nmodel a { input x: f32[N, 4]\n output y = A(x) }\nadapt { tune fc }\n";
        let b = "block B(x) { return sigmoid(x) }\nmodel b { input x: f32[N, 4]\n output y = B(x) }\n";
        let whole = "use \"a.readi\"\nuse \"b.readi\"\nmodel whole { input x: f32[N, 4]\n output y = B(A(x)) }\n";
        let (p, _) = parse_root(vec![("a.readi", a), ("b.readi", b), ("w.readi", whole)], "w.readi");
        assert!(p.diagnostics.is_empty(), "{:?}", p.diagnostics);
        assert_eq!(p.file.blocks().count(), 2);
        let models: Vec<_> = p.file.models().map(|m| m.name.name.as_str()).collect();
        assert_eq!(models, ["whole"]);
        // The part's adapt section still comes along: the assembled file has none.
        assert_eq!(p.file.adapt_sections().count(), 1);
        // Without a model of its own, the using file gets both parts' models.
        let (p, _) = parse_root(
            vec![("a.readi", a), ("b.readi", b), ("u.readi", "use \"a.readi\"\nuse \"b.readi\"\n")],
            "u.readi",
        );
        assert_eq!(p.file.models().count(), 2);
    }

    #[test]
    fn a_file_reached_twice_or_in_a_cycle_is_included_once() {
        let a = "use \"b.readi\"\nuse \"c.readi\"\nmodel m { input x: f32[N, 4]\n output y = B(x) }\n";
        let b = "use \"c.readi\"\nuse \"a.readi\"\n";
        let c = "block B(x) { return relu(x) }\n";
        let (p, _) = parse_root(vec![("a.readi", a), ("b.readi", b), ("c.readi", c)], "a.readi");
        assert!(p.diagnostics.is_empty(), "{:?}", p.diagnostics);
        assert_eq!(p.file.blocks().count(), 1);
        assert_eq!(p.file.models().count(), 1);
    }

    #[test]
    fn an_unreadable_use_and_an_error_in_a_used_file_point_where_they_are() {
        let root = "use \"gone.readi\"\nuse \"bad.readi\"\n";
        let bad = "model m {\n  input x f32[N]\n}\n";
        let (p, map) = parse_root(vec![("r.readi", root), ("bad.readi", bad)], "r.readi");
        let located: Vec<String> =
            p.diagnostics.iter().map(|d| format!("{} {}", map.locate(d.labels[0].span), d.message)).collect();
        assert_eq!(located.len(), 2, "{located:?}");
        assert!(located[0].starts_with("r.readi:1:1 cannot use `gone.readi`: no such file"), "{located:?}");
        assert!(located[1].starts_with("bad.readi:2:"), "{located:?}");
    }
}
