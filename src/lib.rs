//! The `readi` package as a library: the parts of the CLI that are useful as functions.
//! The compiler and the runtime are the `readi-compiler` and `readi-runtime` crates.

pub mod inspect;
pub mod rounds;
pub mod simulate;
