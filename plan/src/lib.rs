//! The vocabulary readi's compiler and runtime share.
//!
//! * [`dim`]: tensor dimensions, known or symbolic (`N`, `6*N`);
//! * [`ops`]: every operator's attributes and shape rule, defined once and used by the
//!   compiler's shape inference and by the runtime's plan check;
//! * [`format`]: the plan manifest (schedule, values, tensors, variant tables), and
//!   [`validate`], the checks a manifest passes before anything runs it;
//! * [`conditions`]: the spec's conditions (axes, selectors, missing policies, meld rule);
//! * [`key`]: variant keys, read and written one way everywhere.
//!
//! The crate depends on nothing but serde, so the compiler's front end can use it without
//! depending on kernel code.

pub mod conditions;
pub mod dim;
pub mod format;
pub mod key;
pub mod ops;
pub mod validate;

pub use dim::{Dim, show_shape};
pub use key::VariantKey;
pub use ops::{DType, TensorType};
