//! `readi ast`: the file as the parser understood it (canonical source, or the raw tree).

use std::path::Path;
use std::process::ExitCode;

use super::frontend::{Frontend, summary_line};

pub fn run(s: &mut Frontend, path: &Path, debug: bool) -> Result<(), ExitCode> {
    let (file, text) = s.load(path)?;
    let parsed = readi_grammar::parse(file, &text);
    s.report(&parsed.diagnostics);
    if parsed.diagnostics.has_errors() {
        eprintln!("error: {}", summary_line(&path.display().to_string(), &parsed.diagnostics));
        return Err(ExitCode::FAILURE);
    }
    if debug {
        println!("{:#?}", parsed.file);
    } else {
        print!("{}", readi_grammar::ast_print::to_source(&parsed.file));
    }
    Ok(())
}
