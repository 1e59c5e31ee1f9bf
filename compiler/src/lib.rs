//! The readi compiler front end: the graph IR ([`ir`]), elaboration of a parsed file into
//! it ([`elaborate`]), the operators' builtins ([`ops`]), the pass pipeline ([`passes`]), the
//! verifier ([`verify`]), selector patterns ([`select`]) and printers ([`print`]).
//!
//! ```
//! use readi_compiler::passes::{self, Options};
//! use readi_grammar::diag::SourceMap;
//!
//! let src = "model m { input x: f32[N, 8] @camera\n fc = linear(x, 4)\n output y = fc }";
//! let mut sources = SourceMap::new();
//! let file = sources.add("m.readi", src);
//! let out = passes::run(file, src, &Options::default());
//! assert!(!out.diagnostics.has_errors());
//! let module = out.module.expect("a module");
//! assert_eq!(module.graph.parameter_count(), 8 * 4 + 4);
//! ```

pub mod adapt;
pub mod backend;
pub mod elaborate;
pub mod ir;
pub mod module;
pub mod ops;
pub mod passes;
pub mod print;
pub mod select;
pub mod value;
pub mod verify;
pub mod weights;

pub use module::Module;
pub use passes::{Options, Outcome, Pass, run};
