//! The front end as the commands use it: loading spec files, running the pipeline,
//! rendering diagnostics, and the one-line error summary.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use readi_compiler::passes::{self, Options, Outcome, Pass};
use readi_grammar::diag::{Diagnostics, FileId, SourceMap};

use super::args::ModelArgs;

/// The loaded source files and how to show their diagnostics.
pub struct Frontend {
    pub sources: SourceMap,
    pub color: bool,
    /// Each file read, by its canonical path, so a file used twice has one id.
    read: Vec<(PathBuf, FileId)>,
}

impl Frontend {
    pub fn new(sources: SourceMap, color: bool) -> Frontend {
        Frontend { sources, color, read: Vec::new() }
    }

    pub fn load(&mut self, path: &Path) -> Result<(FileId, String), ExitCode> {
        self.read_source(path).map_err(|e| {
            eprintln!("error: {e}");
            ExitCode::from(2)
        })
    }

    /// Reads a spec file (at most the parser's limit) as UTF-8 text.
    fn read_source(&mut self, path: &Path) -> Result<(FileId, String), String> {
        // The parser refuses longer sources; reading more would only spend memory.
        let limit = readi_grammar::parser::MAX_SOURCE_BYTES as u64;
        let bytes = super::files::read_bounded(path, limit)?;
        let text = String::from_utf8(bytes).map_err(|e| {
            format!("{} is not UTF-8 text (invalid byte at offset {})", path.display(), e.utf8_error().valid_up_to())
        })?;
        let id = self.sources.add(path.display().to_string(), text.clone());
        if let Ok(canonical) = path.canonicalize() {
            self.read.push((canonical, id));
        }
        Ok((id, text))
    }

    /// The file a `use "path"` in file `from` names: relative to `from`'s directory.
    fn load_used(&mut self, from: FileId, path: &str) -> Result<(FileId, String), String> {
        let base = Path::new(self.sources.name(from)).parent().unwrap_or(Path::new(""));
        let full = base.join(path);
        let canonical = full.canonicalize().map_err(|e| format!("{}: {e}", full.display()))?;
        if let Some(&(_, id)) = self.read.iter().find(|(p, _)| *p == canonical) {
            return Ok((id, self.sources.text(id).to_string()));
        }
        self.read_source(&full)
    }

    pub fn report(&self, diags: &Diagnostics) {
        let mut err = std::io::stderr().lock();
        let _ = err.write_all(self.sources.render_all(diags, self.color).as_bytes());
    }

    /// The number of blocks of `path` when it is a block library: a file that parses (its
    /// uses included) to blocks and no model, which model files `use` and which is
    /// therefore not elaborated on its own. `None` for anything else, and for a file that
    /// cannot be read or does not parse (the full compile then reports why).
    pub fn library_blocks(&mut self, path: &Path) -> Option<usize> {
        let (file, text) = self.read_source(path).ok()?;
        let parsed = readi_grammar::imports::parse_with_uses(file, &text, &mut |from, p| self.load_used(from, p));
        let library = !parsed.diagnostics.has_errors() && parsed.file.models().next().is_none();
        let blocks = parsed.file.blocks().count();
        (library && blocks > 0).then_some(blocks)
    }

    pub fn compile(
        &mut self,
        path: &Path,
        model: &ModelArgs,
        stop_after: Option<Pass>,
    ) -> Result<(Outcome, FileId), ExitCode> {
        let (file, text) = self.load(path)?;
        let opts = options(model, stop_after);
        let out = passes::run_with_uses(file, &text, &opts, &mut |from, path| self.load_used(from, path));
        self.report(&out.diagnostics);
        Ok((out, file))
    }
}

fn options(model: &ModelArgs, stop_after: Option<Pass>) -> Options {
    let mut opts = Options { stop_after, ..Options::with_overrides(&model.set) };
    opts.elab.max_activation_bytes = model.max_activation_memory.map(|b| b as u64);
    opts
}

pub fn summary_line(path: &str, diags: &Diagnostics) -> String {
    let plural = |n: usize, w: &str| format!("{n} {w}{}", if n == 1 { "" } else { "s" });
    let mut parts = Vec::new();
    if diags.error_count() > 0 {
        parts.push(plural(diags.error_count(), "error"));
    }
    if diags.warning_count() > 0 {
        parts.push(plural(diags.warning_count(), "warning"));
    }
    format!("{path}: {}", parts.join(", "))
}

/// Compiles a file and, if that succeeded, hands the module to `f`.
pub fn with_module(
    s: &mut Frontend,
    path: &Path,
    model: &ModelArgs,
    stop_after: Option<Pass>,
    f: impl FnOnce(&readi_compiler::Module),
) -> Result<(), ExitCode> {
    let (out, _) = s.compile(path, model, stop_after)?;
    if out.diagnostics.has_errors() {
        eprintln!("error: {}", summary_line(&path.display().to_string(), &out.diagnostics));
        return Err(ExitCode::FAILURE);
    }
    match &out.module {
        Some(m) => {
            f(m);
            Ok(())
        }
        None => {
            eprintln!("{}: nothing to show after pass `parse`; use `readi ast`", path.display());
            Err(ExitCode::FAILURE)
        }
    }
}
