//! Species specs. Being written.
