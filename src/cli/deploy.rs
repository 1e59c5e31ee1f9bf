//! Deployment manifests: one base model and its variants, in YAML.
//!
//! ```yaml
//! spec: models/resnet18.readi        # paths are relative to this file
//! set: { num_classes: 10 }           # model parameters (optional)
//! weights: resnet18.safetensors      # the base model's state_dict
//! lora: merge                        # or `branch` (optional; default merge)
//! variants:
//!   - key: gamma=0.25                # a key the spec's variants section declares
//!     params: gamma_0.25.safetensors # tensors the variant owns, PyTorch names (optional)
//!     peft: adapters/gamma_0.25      # a PEFT LoRA adapter directory (optional)
//!   - key: blur=5
//!     peft: adapters/blur_5
//! melds: [gamma=0.25+blur=5]          # combined conditions, by the spec's meld rule (optional)
//! ```
//!
//! Unknown fields are errors (a misspelt `varaints` must not silently drop every variant);
//! every error names the file, and YAML errors the line and column.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use readi_compiler::Module;
use readi_compiler::backend::{VariantSource, WeightSet, peft};
use readi_compiler::weights::variants::canonical_key;
use readi_grammar::diag::{Code, Diagnostic, Diagnostics};
use serde::Deserialize;

/// A parsed deployment manifest, paths resolved against its directory.
#[derive(Clone, Debug)]
pub struct Deployment {
    pub spec: PathBuf,
    pub set: Vec<(String, String)>,
    pub weights: PathBuf,
    pub lora: Option<String>,
    pub variants: Vec<VariantFiles>,
    /// Melded variants to build from the listed ones, `fog=0.06+gamma=0.5`.
    pub melds: Vec<String>,
}

/// Where one variant's parameters are: every file given for its key, in order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VariantFiles {
    pub key: String,
    pub files: Vec<VariantFile>,
}

/// One file of a variant's parameters.
#[derive(Clone, Debug, PartialEq)]
pub enum VariantFile {
    /// A safetensors file of the tensors it owns, by PyTorch name.
    Params(PathBuf),
    /// A PEFT LoRA adapter directory.
    Peft(PathBuf),
}

impl VariantFile {
    pub fn path(&self) -> &Path {
        match self {
            VariantFile::Params(p) | VariantFile::Peft(p) => p,
        }
    }
}

use super::files::{MAX_CONFIG_BYTES, MAX_WEIGHTS_BYTES, read_bounded};

/// The variants with the files of each key together, keys in order of first appearance:
/// a key given twice (on the command line, in a manifest, or both) reads all its files.
pub fn group_by_key(entries: impl IntoIterator<Item = (String, VariantFile)>) -> Vec<VariantFiles> {
    let mut out: Vec<VariantFiles> = Vec::new();
    for (key, file) in entries {
        match out.iter_mut().find(|v| v.key == key) {
            Some(v) => v.files.push(file),
            None => out.push(VariantFiles { key, files: vec![file] }),
        }
    }
    out
}

/// [`group_by_key`] again with keys compared by value, now that the spec's declared keys
/// are known: `fog=0.01` and `fog=0.010` are one key, whose files merge. A key the spec
/// does not declare stays as written (binding reports it).
pub fn regroup_by_value(variants: Vec<VariantFiles>, module: &Module) -> Vec<VariantFiles> {
    let declared = module.variants.as_ref().map(|v| v.keys()).unwrap_or_default();
    let mut shown: Vec<(String, String)> = Vec::new();
    let entries: Vec<(String, VariantFile)> = variants
        .into_iter()
        .flat_map(|v| {
            let canonical = canonical_key(&v.key, &declared).map_or_else(|| v.key.clone(), |k| k.to_string());
            // Keep the first spelling given, for messages.
            let key = match shown.iter().find(|(c, _)| *c == canonical) {
                Some((_, first)) => first.clone(),
                None => {
                    shown.push((canonical, v.key.clone()));
                    v.key.clone()
                }
            };
            v.files.into_iter().map(move |f| (key.clone(), f)).collect::<Vec<_>>()
        })
        .collect();
    group_by_key(entries)
}

/// Adds the tensors of one file to a variant's, the one rule for combining a variant's
/// files: files that give disjoint tensors merge; a tensor given by two files is an
/// error naming it and both files (`from` records which file gave each tensor).
pub fn merge_tensors(
    key: &str,
    into: &mut WeightSet,
    from: &mut BTreeMap<String, String>,
    file: &str,
    tensors: WeightSet,
) -> Result<(), Diagnostics> {
    for (name, t) in tensors.tensors {
        if let Some(first) = from.get(&name) {
            return Err(Diagnostics(vec![
                Diagnostic::error(
                    Code::VariantWeights,
                    format!("variant `{key}`: tensor `{name}` is given by both {first} and {file}"),
                )
                .with_note("a key given twice merges its files only when they give different tensors"),
            ]));
        }
        from.insert(name.clone(), file.to_string());
        into.tensors.insert(name, t);
    }
    Ok(())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDeployment {
    spec: PathBuf,
    #[serde(default)]
    set: BTreeMap<String, yaml_serde::Value>,
    weights: PathBuf,
    #[serde(default)]
    lora: Option<String>,
    #[serde(default)]
    variants: Vec<RawVariant>,
    #[serde(default)]
    melds: Vec<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawVariant {
    key: String,
    #[serde(default)]
    params: Option<PathBuf>,
    #[serde(default)]
    peft: Option<PathBuf>,
}

/// Parses a manifest's text; `path` names it in errors and anchors relative paths.
pub fn parse(path: &Path, text: &str) -> Result<Deployment, String> {
    let name = path.display();
    let raw: RawDeployment = yaml_serde::from_str(text).map_err(|e| match e.location() {
        Some(at) => format!("{name}:{}:{}: {e}", at.line(), at.column()),
        None => format!("{name}: {e}"),
    })?;
    let dir = path.parent().unwrap_or(Path::new(""));
    let resolve = |p: PathBuf| if p.is_absolute() { p } else { dir.join(p) };
    let mut set = Vec::new();
    for (k, v) in raw.set {
        let value = match v {
            yaml_serde::Value::Number(n) => n.to_string(),
            yaml_serde::Value::Bool(b) => b.to_string(),
            yaml_serde::Value::String(s) => s,
            _ => return Err(format!("{name}: `set.{k}` must be a number, a boolean or a string")),
        };
        set.push((k, value));
    }
    let mut entries = Vec::new();
    for (i, v) in raw.variants.into_iter().enumerate() {
        if v.params.is_none() && v.peft.is_none() {
            return Err(format!("{name}: variant {} (`{}`) gives neither `params` nor `peft`", i + 1, v.key));
        }
        entries.extend(v.params.map(|p| (v.key.clone(), VariantFile::Params(resolve(p)))));
        entries.extend(v.peft.map(|p| (v.key.clone(), VariantFile::Peft(resolve(p)))));
    }
    let variants = group_by_key(entries);
    Ok(Deployment {
        spec: resolve(raw.spec),
        set,
        weights: resolve(raw.weights),
        lora: raw.lora,
        variants,
        melds: raw.melds,
    })
}

fn read(path: &Path) -> Result<Vec<u8>, Diagnostics> {
    read_bounded(path, MAX_WEIGHTS_BYTES).map_err(|e| Diagnostics(vec![Diagnostic::error(Code::VariantWeights, e)]))
}

/// Reads a variant's files into one set of tensors by readi name, merged by
/// [`merge_tensors`].
pub fn read_variant(files: &VariantFiles, module: &Module) -> Result<VariantSource, Diagnostics> {
    let mut weights = WeightSet::default();
    let mut from = BTreeMap::new();
    let mut origin = Vec::new();
    for file in &files.files {
        let name = file.path().display().to_string();
        let tensors = match file {
            VariantFile::Params(p) => WeightSet::from_safetensors(&name, &read(p)?)?,
            VariantFile::Peft(dir) => {
                let config = read_bounded(&dir.join(peft::CONFIG_FILE), MAX_CONFIG_BYTES)
                    .map_err(|e| Diagnostics(vec![Diagnostic::error(Code::VariantWeights, e)]))?;
                let config = String::from_utf8_lossy(&config).into_owned();
                peft::read_adapter(&name, &config, &read(&dir.join(peft::WEIGHTS_FILE))?, module)?
            }
        };
        merge_tensors(&files.key, &mut weights, &mut from, &name, tensors)?;
        origin.push(name);
    }
    Ok(VariantSource { key: files.key.clone(), weights, origin: origin.join(" + ") })
}

/// `KEY=PATH` from the command line: a directory is a PEFT adapter, a file a parameter
/// file. Giving a key twice combines its files ([`group_by_key`]).
pub fn variant_args(args: &[(String, String)]) -> Vec<VariantFiles> {
    group_by_key(args.iter().map(|(key, path)| (key.clone(), variant_file(path))))
}

/// The command line's files, each with its key, ungrouped (to group with a manifest's).
pub fn variant_arg_files(args: &[(String, String)]) -> Vec<(String, VariantFile)> {
    args.iter().map(|(key, path)| (key.clone(), variant_file(path))).collect()
}

fn variant_file(path: &str) -> VariantFile {
    let path = PathBuf::from(path);
    if path.is_dir() { VariantFile::Peft(path) } else { VariantFile::Params(path) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_manifest_resolves_paths_against_its_directory() {
        let text = "spec: m.readi\nset: {num_classes: 10, img: 64}\nweights: w.safetensors\nvariants:\n  - key: fog=0.03\n    params: fog.safetensors\n  - key: gamma=0.5\n    peft: adapters/g\n";
        let d = parse(Path::new("deploy/x.yaml"), text).expect("parses");
        assert_eq!(d.spec, Path::new("deploy/m.readi"));
        assert_eq!(d.weights, Path::new("deploy/w.safetensors"));
        assert_eq!(d.set, vec![("img".to_string(), "64".to_string()), ("num_classes".to_string(), "10".to_string())]);
        assert_eq!(d.variants.len(), 2);
        assert_eq!(d.variants[0].files, [VariantFile::Params("deploy/fog.safetensors".into())]);
        assert_eq!(d.variants[1].files, [VariantFile::Peft("deploy/adapters/g".into())]);
    }

    #[test]
    fn a_misspelt_field_is_an_error_with_its_place() {
        let text = "spec: m.readi\nweights: w.safetensors\nvaraints: []\n";
        let e = parse(Path::new("d.yaml"), text).expect_err("unknown field");
        assert!(e.starts_with("d.yaml:3:1:") && e.contains("varaints"), "{e}");
    }

    #[test]
    fn a_variant_without_files_is_an_error() {
        let text = "spec: m.readi\nweights: w.safetensors\nvariants:\n  - key: fog=0.03\n";
        let e = parse(Path::new("d.yaml"), text).expect_err("no files");
        assert!(e.contains("neither `params` nor `peft`"), "{e}");
    }
}
