//! The readi language front end: the pest grammar (`readi.pest`), the typed AST with
//! source spans, the parser with error recovery, and diagnostics rendering.
//!
//! ```
//! use readi_grammar::{diag::SourceMap, parse};
//! let mut sources = SourceMap::new();
//! let src = "model m { input x: f32[N, 4] }";
//! let file = sources.add("m.readi", src);
//! let parsed = parse(file, src);
//! assert!(parsed.diagnostics.is_empty());
//! assert_eq!(parsed.file.models().count(), 1);
//! ```

pub mod ast;
pub mod ast_print;
pub mod diag;
pub mod imports;
pub mod parser;

pub use parser::{Parsed, parse};
