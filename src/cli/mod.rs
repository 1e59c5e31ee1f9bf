//! The commands of `readi`, one module per command; `main.rs` parses the command line
//! and dispatches to them.

pub mod adapt_bn;
pub mod demo;
pub mod deploy;
pub mod tensor_io;
